"""The evaluation's methods (DESIGN 4.4): each a vocabulary kind and a scorer, by the paper's names.

Plain Python on purpose: ``aefabmap_eval --help`` lists them without importing the evaluation.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

from aefabmap_ros.errors import ConfigError

# Method name -> (vocabulary kind, scorer).
METHODS: dict[str, tuple[str, str]] = {
    "FABMAP2": ("kmeans", "fabmap"),
    "AE-FABMAP": ("autoencoder", "fabmap"),
    "BoW": ("kmeans", "tfidf"),
    "AE-BoW": ("autoencoder", "tfidf"),
}


def method_kinds() -> tuple[str, ...]:
    """The vocabulary kinds the methods use, in the order of ``METHODS`` (the order they are trained in)."""
    return tuple(dict.fromkeys(kind for kind, _ in METHODS.values()))


def parse_methods(names: Iterable[str]) -> tuple[str, ...]:
    """Canonical method names (case-insensitive, order of ``METHODS``); ConfigError naming an unknown one."""
    by_lower = {name.lower(): name for name in METHODS}
    chosen = set()
    for name in names:
        canonical = by_lower.get(name.strip().lower())
        if canonical is None:
            raise ConfigError(f"unknown method {name!r}; known: {', '.join(METHODS)}")
        chosen.add(canonical)
    if not chosen:
        raise ConfigError(f"no method selected; known: {', '.join(METHODS)}")
    return tuple(name for name in METHODS if name in chosen)


def methods_of_kind(kind: str, selected: Sequence[str]) -> tuple[str, ...]:
    """The selected methods that use a vocabulary of ``kind``."""
    return tuple(name for name in selected if METHODS[name][0] == kind)
