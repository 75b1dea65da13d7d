"""The compiled estimator as a prebuilt extension module, so the node process never loads numba's LLVM.

numba's JIT costs a process ~130 MiB (LLVM) even when it only loads cached code. The same source
(estimate_kernel.py and its siblings) is therefore compiled ahead of time with numba.pycc, once per
machine, in a subprocess, into a cache directory named by a fingerprint of the sources and the toolchain;
later starts just import it.
If the build cannot be done here (no C compiler, a read-only cache), the caller falls back to the JIT.
Each new build removes the builds no process has loaded for a month (`prune`).

    python -m profile_pose_ros.core.compiled.aot build    # build now (e.g. in a container image)
"""
from __future__ import annotations

import contextlib
import fcntl
import importlib.machinery
import importlib.util
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from .caches import cache_root, fingerprint, prune

MODULE = "profile_pose_estimator_aot"
JIT_CACHE = ".numba"  # inside a build's scratch directory: the JIT cache its compilation starts empty


def build_dir() -> Path:
    """Where this machine's build of the current sources is (or would be)."""
    return cache_root() / fingerprint()


def _module_file(directory: Path) -> Path | None:
    for suffix in importlib.machinery.EXTENSION_SUFFIXES:
        candidate = directory / (MODULE + suffix)
        if candidate.is_file():
            return candidate
    return None


def _import(path: Path):
    spec = importlib.util.spec_from_file_location(MODULE, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def ensure_built(timeout: float = 900.0) -> Path | None:
    """This machine's build of the kernel, built now (a minute or so, in a subprocess) if there is none;
    None if it cannot be built here. A tool calls it before it starts an estimator process, so that the
    node does not spend its start-up compiling while the tool waits for poses."""
    target = build_dir()
    path = _module_file(target)
    if path is not None:
        try:
            os.utime(target)  # in use: prune() keeps it
        except OSError:
            pass
        return path
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        with _one_build_at_a_time(target.parent / "build.lock", timeout):
            if _module_file(target) is None:  # not built by the process this one waited for
                _build(target, timeout)
    except (OSError, subprocess.SubprocessError, TimeoutError):
        return None
    return _module_file(target)


@contextlib.contextmanager
def _one_build_at_a_time(lock_file: Path, timeout: float):
    """Held while a build runs: processes that need the kernel at once on a new machine (two nodes started
    together, a script and the node it starts) wait for one build instead of each making its own on the
    same cores. Polled, so that a wait ends at its timeout (TimeoutError)."""
    deadline = time.monotonic() + timeout
    with open(lock_file, "a") as handle:
        while True:
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    raise TimeoutError(f"another build held {lock_file} for {timeout:g} s") from None
                time.sleep(0.2)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def _build(target: Path, timeout: float) -> None:
    """Build into a scratch directory beside target, then rename it to target (atomic)."""
    scratch = Path(tempfile.mkdtemp(prefix=target.name + ".", dir=target.parent))
    # the build compiles every kernel afresh, with a JIT cache of its own (see caches.jit_cache)
    fresh = {**os.environ, "NUMBA_CACHE_DIR": str(scratch / JIT_CACHE)}
    done = subprocess.run([sys.executable, "-m", "profile_pose_ros.core.compiled.aot", "build", str(scratch)],
                          capture_output=True, text=True, timeout=timeout, env=fresh)
    shutil.rmtree(scratch / JIT_CACHE, ignore_errors=True)
    if done.returncode == 0 and _module_file(scratch) is not None:
        try:
            scratch.rename(target)  # atomic
        except OSError:
            pass
    shutil.rmtree(scratch, ignore_errors=True)
    prune(target.parent, keep=target)


def is_current() -> bool:
    """Whether this machine has a build of the current sources."""
    return _module_file(build_dir()) is not None


def load(timeout: float = 900.0):
    """The prebuilt kernel module, building it first if needed; None if that is not possible here."""
    path = ensure_built(timeout)
    if path is None:
        return None
    try:
        return _import(path)
    except ImportError:
        return None


def build_into(directory: Path) -> None:
    """Compile profile_kernel.estimate, estimate_kernel.refine_pose and .detect, decode_kernel.decode_xz and
    dense_kernel.refine_dense with numba.pycc (in its own process: it loads LLVM)."""
    import warnings

    from numba import types

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from numba.pycc import CC

    from . import decode_kernel, dense_kernel, estimate_kernel, profile_kernel

    f8 = types.float64
    array2, array1 = types.Array(f8, 2, "C"), types.Array(f8, 1, "C")
    frozen2, frozen1 = types.Array(f8, 2, "C", readonly=True), types.Array(f8, 1, "C", readonly=True)
    boolean, int64 = types.boolean, types.int64
    frozen4 = types.Array(f8, 4, "C", readonly=True)
    signature = types.Tuple((int64, int64, f8, f8, f8, f8, int64, int64, int64, int64, int64, int64))(
        array2, frozen2, frozen1, frozen1, array2, array1, array1, array1, f8, f8, frozen1, frozen2, frozen4, f8, f8,
        array2, array2, array1, array2, array2, array1, array2, array2, array1, array1)
    compiler = CC(MODULE)
    compiler.output_dir = str(directory)
    compiler.target_cpu = "host"  # built on the machine that runs it

    @compiler.export("estimate", signature)
    def estimate(points, q, u, w, normals, offsets, ridge_q, ridge_u, width, length, opt, partial_opt, tables,
                 max_sigma, margin, corners, rot, t, cov, cf_rot, cf_t, cf_res, res, info, where):
        return profile_kernel.estimate(points, q, u, w, normals, offsets, ridge_q, ridge_u, width, length, opt,
                                       partial_opt, tables, max_sigma, margin, corners, rot, t, cov, cf_rot, cf_t,
                                       cf_res, res, info, where)

    refine_signature = types.Tuple((int64, int64))(
        frozen2, frozen1, frozen1, array2, array2, array1, array2, boolean, int64, boolean, array2, array1, array1,
        array2)

    @compiler.export("refine_pose", refine_signature)
    def refine_pose(q, u, w, corners, rot, t, corner_cov, weighted, max_iterations, polish, rot_out, t_out, r_out,
                    cov_out):
        return estimate_kernel.refine_pose(q, u, w, corners, rot, t, corner_cov, weighted, max_iterations, polish,
                                           rot_out, t_out, r_out, cov_out)

    detect_signature = types.Tuple((int64, int64, f8))(array2, int64, frozen1, array2, array2, array1, array1, array2)

    @compiler.export("detect", detect_signature)
    def detect(points, n_corners, opt, corners, jac, line_var, info, lines_out):
        return estimate_kernel.detect(points, n_corners, opt, corners, jac, line_var, info, lines_out)

    table = types.Array(types.float32, 2, "C", readonly=True)

    @compiler.export("decode_xz", types.Tuple((int64, int64))(table, int64, int64, int64, array2))
    def decode_xz(table, x_col, y_col, z_col, out):
        return decode_kernel.decode_xz(table, x_col, y_col, z_col, out)

    dense_signature = types.Tuple((int64, int64, f8))(
        array2, array2, array1, array1, array1, f8, f8, array2, array1, f8, f8, f8, f8, int64, array2, array1, array2)

    @compiler.export("refine_dense", dense_signature)
    def refine_dense(points, normals, offsets, ridge_q, ridge_u, width, length, rot, t, noise_std, margin, threshold,
                     floor, iterations, rot_out, t_out, cov_out):
        return dense_kernel.refine_dense(points, normals, offsets, ridge_q, ridge_u, width, length, rot, t, noise_std,
                                         margin, threshold, floor, iterations, rot_out, t_out, cov_out)

    compiler.compile()


def main(argv=None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if args[:1] != ["build"]:
        print(__doc__)
        return 2
    if len(args) > 1:
        build_into(Path(args[1]))
        return 0
    module = load()
    print(f"{MODULE}: {'ready' if module else 'could not be built here'} in {build_dir()}")
    return 0 if module else 1


if __name__ == "__main__":
    sys.exit(main())
