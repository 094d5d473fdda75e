"""scripts/gpu_bundle.sh: wheels packed into carry-sized parts that, joined in order on the device, unpack into an
importable site-packages folder (docs/gpu.md)."""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "gpu_bundle.sh"


def _fake_wheel(path: Path, package: str, payload: bytes) -> None:
    with zipfile.ZipFile(path, "w") as z:
        z.writestr(f"{package}/__init__.py", f"VALUE = {len(payload)}\n")
        z.writestr(f"{package}/blob.bin", payload)
        z.writestr(f"{package}-1.0.dist-info/METADATA", f"Name: {package}\nVersion: 1.0\n")


def test_parts_join_into_an_importable_site(tmp_path):
    wheels = tmp_path / "wheels"
    wheels.mkdir()
    rng = os.urandom  # incompressible, so that the bundle needs several 1 MB parts
    _fake_wheel(wheels / "fake_a-1.0-py3-none-any.whl", "fake_a", rng(1_500_000))
    _fake_wheel(wheels / "fake_b-1.0-py3-none-any.whl", "fake_b", rng(700_000))
    out = tmp_path / "bundle"
    done = subprocess.run([str(SCRIPT), "--wheels", str(wheels), "--part-mb", "1", "--out", str(out)],
                          capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert done.returncode == 0, done.stderr
    parts = sorted(out.glob("p*"), key=lambda p: int(p.name[1:]))
    assert len(parts) == 3 and all(p.stat().st_size <= 1_000_000 for p in parts)
    assert "call 3:" in done.stdout and "call 1:" in done.stdout
    # the device's side: the parts in order, xz -dc, tar -x
    site = tmp_path / "site"
    site.mkdir()
    joined = b"".join(p.read_bytes() for p in parts)
    unpack = subprocess.run(["bash", "-c", f"xz -dc | tar -xf - -C {site}"], input=joined, capture_output=True,
                            timeout=120)
    assert unpack.returncode == 0, unpack.stderr
    check = subprocess.run([sys.executable, "-c", "import fake_a, fake_b; print(fake_a.VALUE, fake_b.VALUE)"],
                           capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(site)}, timeout=60)
    assert check.stdout.split() == ["1500000", "700000"], check.stderr


def test_bad_arguments_exit_2(tmp_path):
    for args, message in ((["--part-mb", "100"], "outside 1..60"), (["--part-mb", "x"], "whole number"),
                          (["--bogus"], "unknown argument"), (["--wheels", str(tmp_path)], "no *.whl")):
        done = subprocess.run([str(SCRIPT), *args, "--out", str(tmp_path / "o")], capture_output=True, text=True,
                              cwd=ROOT, timeout=60)
        assert done.returncode == 2 and message in done.stderr, (args, done.stderr)


def test_gpu_kernel_cache_compiles_modules_for_a_gpu_without_one(tmp_path):
    """``scripts/gpu_kernel_cache.py`` compiles Warp modules for sm_90 here (Warp's NVRTC, no driver) into Warp's
    cache layout: one cubin and its meta per module, named by the module's hash, no ``.cu`` left; ``--list`` names
    every ``kernels/`` module with Warp code and leaves out the CPU-only queue; an architecture this Warp cannot
    target exits 2."""
    import warp as wp

    wp.init()
    if 90 not in set(getattr(wp._src.context.runtime, "nvrtc_supported_archs", None) or ()):
        pytest.skip("this Warp build has no NVRTC for sm_90")
    script = str(ROOT / "scripts" / "gpu_kernel_cache.py")
    out = tmp_path / "cache"
    done = subprocess.run([sys.executable, script, "--out", str(out), "--modules", "kernels.free_flight",
                           "kernels.cell_list"], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    files = sorted(p.name for p in out.rglob("*") if p.is_file())
    cubins = [f for f in files if f.endswith(".sm90.cubin")]
    assert len(cubins) == 2
    assert {c.rsplit("_", 1)[0] for c in cubins} == {"wp_kernels.free_flight", "wp_kernels.cell_list"}
    assert {f.rsplit(".", 2)[0] for f in cubins} == {f[: -len(".meta")] for f in files if f.endswith(".meta")}
    assert not any(f.endswith(".cu") for f in files)
    listed = subprocess.run([sys.executable, script, "--list"], capture_output=True, text=True, timeout=600)
    names = listed.stdout.split()
    assert {"kernels.gas", "kernels.forest", "kernels.cell_collide", "kernels.deposit"} <= set(names)
    assert "kernels.swept_queue" not in names
    bad = subprocess.run([sys.executable, script, "--arch", "30", "--out", str(out)], capture_output=True, text=True)
    assert bad.returncode == 2
