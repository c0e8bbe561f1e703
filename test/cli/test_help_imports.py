"""--help and usage errors answer before the heavy libraries load (the work is imported after parsing)."""

import subprocess
import sys

import pytest

HEAVY = ("torch", "numba", "cv2", "faiss", "sklearn", "gtsam", "evo", "scipy")

PROBE = """
import sys
from importlib import import_module
main = import_module(sys.argv[1]).main
for argv in (["--help"], ["--no-such-option"]):
    try:
        main(argv)
    except SystemExit:
        pass
print("loaded:" + ",".join(name for name in sys.argv[2].split(",") if name in sys.modules))
"""


HEAVY_WORK_CLIS = ("train", "evaluate", "bench", "gt", "words", "map")


@pytest.mark.parametrize("module", [f"aefabmap_ros.cli.{name}" for name in HEAVY_WORK_CLIS])
def test_help_and_usage_errors_import_no_heavy_library(module):
    result = subprocess.run([sys.executable, "-c", PROBE, module, ",".join(HEAVY)], capture_output=True, text=True,
                            timeout=120, check=True)
    assert result.stdout.strip().splitlines()[-1] == "loaded:"
    assert "usage:" in result.stdout + result.stderr or module.endswith("bench")


CLIS = ("train", "evaluate", "gt", "synth", "bag", "ate", "launch", "replay", "record", "demo", "words", "map")


@pytest.mark.parametrize("name", CLIS)
def test_a_usage_error_is_one_error_line_and_exit_1(name, capsys):
    """Every CLI maps a bad option the same way (argparse alone would exit 2 with its own message)."""
    from importlib import import_module

    assert import_module(f"aefabmap_ros.cli.{name}").main(["--no-such-option"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("ERROR: ") and "usage: aefabmap_" in err  # the missing argument or the unknown option
