"""Compile the engine's Warp modules for a GPU here, without one, into a kernel cache to carry to it.

A lent GPU machine starts bare: every process there compiles every CUDA module first (~120 s on an H200), which can
take a short time-limited run's whole budget. Warp's NVRTC is in
its own library, so the modules compile here for the GPU's architecture (``wp.compile_aot_module``) into Warp's
cache layout (``OUT/<warp version>/wp_<module>_<hash>/...<arch>.cubin``). Carry OUT to the GPU and point Warp at it
there with ``WARP_CACHE_PATH=OUT``: an H200 then loads every module in 7.6 s.

Which form the GPU loads: Warp takes cubins when the driver's CUDA is older than Warp's NVRTC (the H200's driver
580 is CUDA 13.0, Warp 1.19's NVRTC 13.4: sm_90 cubins, this script's default) and PTX otherwise (``--ptx``). A
module whose options change at run time (``kernels/deposit.py``'s record budget at weights >= 4) or a kernel defined
at run time still compiles there. The ``.cu`` sources are dropped (half the size).

    python scripts/gpu_kernel_cache.py [--arch 90] [--ptx] [--out .gpuc/cache] [--jobs 2] [--modules NAME ...] [--list]

Exit 2 when Warp has no NVRTC here or a module fails to compile.
"""

from __future__ import annotations

import argparse
import importlib
import os
import subprocess
import sys
import time

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

IMPORTS = ("hel_warp.hel", "hel_warp.gas.solver", "hel_warp.gas.multigrid", "hel_warp.collisions.cells", "hel_warp.collisions.models",
           "hel_warp.collisions.dem", "hel_warp.collisions.cfd_dem", "cases.colliding_streams", "cases.homogeneous_cooling", "bench_rig",
           "profile_step")
"""Modules imported besides every ``kernels/`` module (``hel_warp.runs.run.import_kernel_modules``): they define Warp
kernels of their own or import the modules that do."""


def engine_modules() -> list:
    """Every Warp module with kernels that the engine, the cases and the benches import, less the CPU-only ones."""
    import warp as wp

    from hel_warp.runs.run import CPU_ONLY_MODULES, import_kernel_modules

    import_kernel_modules(cpu=False)
    for name in IMPORTS:
        try:
            importlib.import_module(name)
        except ImportError:
            pass
    registry = wp._src.context.user_modules
    return [m for name, m in registry.items() if name not in CPU_ONLY_MODULES]


def compile_modules(names: list[str] | None, out: str, arch: int, ptx: bool) -> int:
    """Compile ``names`` (None: every engine module) into ``out``; print one line per module; 0, or 2 on a failure."""
    import warp as wp

    wp.config.kernel_cache_dir = out
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    runtime = wp._src.context.runtime
    archs = set(getattr(runtime, "nvrtc_supported_archs", None) or ())
    if not runtime.is_cuda_enabled or arch not in archs:
        print(f"gpu_kernel_cache: this Warp cannot compile for sm_{arch} (a CUDA build of warp-lang compiles for "
              f"{sorted(archs) or 'none'})", file=sys.stderr)
        return 2
    failed = 0
    for module in engine_modules():
        if names is not None and module.name not in names:
            continue
        start = time.perf_counter()
        try:
            wp.compile_aot_module(module, device=None, arch=arch, use_ptx=ptx)
        except Exception as exc:  # noqa: BLE001  (Warp raises plain RuntimeError / ValueError)
            if "No compilable kernels" in str(exc):  # generic kernels only: compiled where they are used
                continue
            print(f"gpu_kernel_cache: {module.name} failed: {exc}", file=sys.stderr)
            failed = 1
            continue
        print(f"{module.name} {time.perf_counter() - start:.1f} s", flush=True)
    for folder, _, files in os.walk(out):
        for f in files:
            if f.endswith(".cu"):
                os.remove(os.path.join(folder, f))
    return 2 if failed else 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--arch", type=int, default=90, help="the GPU's compute capability x 10 (H100 / H200: 90)")
    ap.add_argument("--ptx", action="store_true", help="PTX instead of cubins (a driver at least as new as NVRTC)")
    ap.add_argument("--out", default=os.path.join(ROOT, ".gpuc", "cache"),
                    help="the cache folder to carry (default .gpuc/cache; list /.gpuc/ in .git/info/exclude)")
    ap.add_argument("--jobs", type=int, default=1, help="processes compiling side by side (default 1)")
    ap.add_argument("--modules", nargs="+", default=None, help="only these Warp modules (e.g. kernels.gas)")
    ap.add_argument("--list", action="store_true", help="print the modules it would compile, one line, and stop")
    args = ap.parse_args(argv)
    if args.list:
        import warp as wp

        wp.config.log_level = wp.LOG_WARNING
        print(" ".join(m.name for m in engine_modules()))
        return 0
    if args.arch < 50 or args.jobs < 1:
        ap.exit(2, "gpu_kernel_cache: --arch is a compute capability x 10 (e.g. 90) and --jobs >= 1\n")
    out = os.path.abspath(args.out)
    os.makedirs(out, exist_ok=True)
    start = time.perf_counter()
    if args.jobs == 1 or args.modules is not None:
        rc = compile_modules(args.modules, out, args.arch, args.ptx)
    else:  # split the modules between processes (each compiles with one thread)
        listing = subprocess.run([sys.executable, os.path.abspath(__file__), "--list"], capture_output=True, text=True)
        names = listing.stdout.split()
        if listing.returncode != 0 or not names:
            print(f"gpu_kernel_cache: could not list the modules: {listing.stderr[-500:]}", file=sys.stderr)
            return 2
        base = [sys.executable, os.path.abspath(__file__), "--arch", str(args.arch), "--out", out]
        if args.ptx:
            base.append("--ptx")
        procs = [subprocess.Popen(base + ["--modules", *names[k::args.jobs]]) for k in range(args.jobs)]
        rc = max(p.wait() for p in procs)
    size = sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(out) for f in fs)
    print(f"gpu_kernel_cache: sm_{args.arch} {'PTX' if args.ptx else 'cubins'} in {out} ({size / 1e6:.1f} MB, "
          f"{time.perf_counter() - start:.0f} s); on the GPU: export WARP_CACHE_PATH=<that folder as carried>")
    return rc


if __name__ == "__main__":
    sys.exit(main())
