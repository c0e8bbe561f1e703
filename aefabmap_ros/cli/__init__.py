"""The command-line tools (console scripts aefabmap_*): options and error reporting here, the work in the library.

A tool whose work is heavy keeps its options in ``<tool>.py`` and its work in ``<tool>_run.py``, imported
only after parsing, so ``--help`` answers at once."""

__all__ = [
    "ate",
    "bag",
    "bench",
    "bench_backend",
    "bench_fabmap",
    "bench_nodes",
    "bench_pipeline",
    "bench_processes",
    "bench_stages",
    "bench_verify",
    "bench_view",
    "bench_vocab",
    "common",
    "demo",
    "demo_backend",
    "demo_printer",
    "evaluate",
    "evaluate_depth",
    "evaluate_outputs",
    "evaluate_recording",
    "evaluate_run",
    "gt",
    "gt_run",
    "launch",
    "record",
    "replay",
    "replay_messages",
    "synth",
    "train",
    "train_run",
    "view",
]
