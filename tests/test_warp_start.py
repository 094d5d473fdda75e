"""Warp's start-up: a machine without a GPU runs every command on the CPU without Warp's "Could not find or load
the NVIDIA CUDA driver" line (printed by its native library on the C stderr, no Python setting turns it off); a
command that asks for a CUDA device where there is none still says why, in one line."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DRIVER_LINE = "Could not find or load the NVIDIA CUDA driver"


def _python(code):
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})


def test_the_driver_line_is_dropped_and_every_other_line_kept(capfd):
    # the filter works on file descriptor 2 (where the native library writes), and passes everything else through
    from hel_warp._warp import _without_driver_warning

    with _without_driver_warning():
        os.write(2, f"Warp CUDA warning: {DRIVER_LINE}. GPU execution will not be available.\n".encode())
        os.write(2, b"Warp CUDA error: something else\n")
        print("python stderr", file=sys.stderr)
    err = capfd.readouterr().err
    assert DRIVER_LINE not in err
    assert "Warp CUDA error: something else" in err and "python stderr" in err


def test_a_command_on_the_cpu_prints_no_driver_warning():
    done = subprocess.run([sys.executable, "-m", "hel_warp.cli", "impact"], capture_output=True, text=True, cwd=ROOT,
                          timeout=300, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert done.returncode == 0, done.stderr
    assert "restitution" in done.stdout and DRIVER_LINE not in done.stderr and done.stderr == "", done.stderr


def test_asking_for_cuda_without_a_gpu_keeps_the_reason():
    import warp as wp

    if wp.is_cuda_available():
        pytest.skip("a GPU is present: asking for cuda succeeds")
    done = _python("from hel_warp._warp import init_warp\n"
                   "from hel_warp.errors import ConfigError\n"
                   "try:\n    init_warp('cuda')\nexcept ConfigError as e:\n    print(e)\n")
    assert "--device cpu" in done.stdout and DRIVER_LINE in done.stderr, (done.stdout, done.stderr)
    # the run's device check (its first start asks for no device) names the missing driver in its one line
    done = _python("from hel_warp.runs.run import check_device\n"
                   "from hel_warp.errors import ConfigError\n"
                   "try:\n    check_device('cuda')\nexcept ConfigError as e:\n    print(e)\n")
    assert "no CUDA device" in done.stdout and "driver" in done.stdout and "--device cpu" in done.stdout
