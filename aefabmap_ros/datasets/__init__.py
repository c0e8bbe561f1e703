"""Sample data made by the package itself, outside the library: the synthetic town."""

__all__ = ["synth"]
