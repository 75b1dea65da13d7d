"""The prebuilt estimator (numba.pycc, no LLVM in the process) and numba's JIT are the same code: they must
give the same numbers, and importing the core for the prebuilt kernel must not load numba."""
import os
import subprocess
import sys

import numpy as np
import pytest

from profile_pose_ros.core import EstimatorOptions, render_profile, sample_pose
from profile_pose_ros.core.compiled import aot, caches
from profile_pose_ros.core.compiled import profile_kernel
from profile_pose_ros.core.compiled.codes import PARTIAL_NONE
from profile_pose_ros.core.design.gauge_design import random_gauge
from profile_pose_ros.core.estimation.hidden_face import partial_view_inputs
from profile_pose_ros.core.estimation.result import position_sigma
from profile_pose_ros.core.model.render import true_corners
from profile_pose_ros.tools.robustness import with_gap


def run(kernel, points, gauge, options):
    n = gauge.n_ridges
    # NaN where a call writes nothing (a partial view's rows beyond the corners it saw)
    outs = [np.full(shape, np.nan) for shape in ((n, 2), (3, 3), 3, (6, 6), (3, 3), 3, (n, 2), (n, 2))]
    outs += [np.zeros(4), np.full(6, np.nan)]
    status = kernel(points, gauge.q, gauge.u, gauge.w, *gauge.kernel_faces, gauge.width, gauge.length,
                    options.kernel_vector, *partial_view_inputs(gauge, options), *outs)
    return status, outs


def test_prebuilt_and_jit_kernels_agree(gauge, rng):
    """On the shipped gauge (one call, well determined) and on random five-ridge gauges, where about half
    the poses are poorly determined and the basin search runs inside the call; with the corner model and
    with the dense refinement in the same call; and on every third profile a gap, whose partial view (a face
    it hides, faces out of view) is tried in the same call too."""
    module = aot.load()
    assert module is not None, "the prebuilt estimator could not be built on this machine"
    searched = partial = 0
    for k, other in enumerate([gauge] + [random_gauge(5, rng) for _ in range(3)]):
        options = EstimatorOptions(refine_model=("corners", "dense")[k % 2])
        for i in range(15):
            rotation, t = sample_pose(other, rng)
            points = render_profile(other, rotation, t, noise_std=5e-6, rng=rng)
            if i % 3 == 0:
                points = with_gap(points, true_corners(other, rotation, t)[:, 0], ("over", "between")[i % 2], rng)
            (status_a, outs_a), (status_j, outs_j) = (run(module.estimate, points, other, options),
                                                      run(profile_kernel.estimate, points, other, options))
            assert status_a[0] == status_j[0] and status_a[6:] == status_j[6:]  # same decision, search, hypothesis
            searched += status_a[6] > 0
            partial += status_a[8] != PARTIAL_NONE
            if status_a[0] == 0:
                # the compiled largest position standard deviation is estimator.position_sigma's
                assert status_a[5] == status_j[5] == pytest.approx(position_sigma(outs_a[3][:3, :3]), rel=1e-12)
            for a, j in zip(outs_a, outs_j):
                assert np.allclose(a, j, rtol=1e-12, atol=1e-15, equal_nan=True)
    assert searched > 0 and partial > 0
    status, _ = run(module.estimate, np.full((100, 2), np.nan), gauge, EstimatorOptions())
    assert status[0] != 0 and np.isnan(status[5])


def test_node_side_import_does_not_load_numba(gauge):
    code = ("import sys; from profile_pose_ros.core import Gauge; from profile_pose_ros.core.estimation.estimator "
            f"import warm_up; warm_up(Gauge.from_yaml({str(gauge.source)!r})); "
            "from profile_pose_ros.core.compiled import loader; print(loader.kernel_name(), 'numba' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600).stdout.split()
    assert out[-1] == "False" and "aot" in " ".join(out)


def test_prune_removes_builds_unused_for_a_month_and_dead_scratch_only(tmp_path):
    now = 1_800_000_000.0
    ages = {"aaaa": 40 * 86400, "bbbb": 5 * 86400, "cccc.x1": 2 * 86400, "dddd.x2": 3600, "keep": 90 * 86400}
    for name, age in ages.items():
        (tmp_path / name).mkdir()
        os.utime(tmp_path / name, (now - age, now - age))
    (tmp_path / "a_file").write_text("not a build")
    removed = caches.prune(tmp_path, keep=tmp_path / "keep", now=now)
    assert sorted(p.name for p in removed) == ["aaaa", "cccc.x1"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file", "bbbb", "dddd.x2", "keep"]


def test_a_process_that_needs_the_kernel_while_another_builds_it_waits_for_that_build(tmp_path, monkeypatch):
    """Two processes that need the prebuilt kernel at once on a new machine make one build, not two on the same
    cores: the second waits for the first's lock and then finds its module (a stand-in here: the holder writes the
    file a build would), or gives up at its timeout."""
    import importlib.machinery
    import threading

    monkeypatch.setenv("PROFILE_POSE_AOT_DIR", str(tmp_path))
    target = aot.build_dir()
    built = target / (aot.MODULE + importlib.machinery.EXTENSION_SUFFIXES[0])

    def build_again(*_args) -> None:
        raise AssertionError("built a second time")

    monkeypatch.setattr(aot, "_build", build_again)
    holder = subprocess.Popen([sys.executable, "-c", (
        "import fcntl, pathlib, sys; lock = open(sys.argv[1], 'a'); fcntl.flock(lock, fcntl.LOCK_EX); "
        "print('held', flush=True); sys.stdin.readline(); target = pathlib.Path(sys.argv[2]); "
        "target.parent.mkdir(parents=True); target.write_bytes(b''); fcntl.flock(lock, fcntl.LOCK_UN)"),
        str(tmp_path / "build.lock"), str(built)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        assert aot.ensure_built(timeout=0.3) is None  # held past its timeout: gives up, builds nothing
        found = []
        waiter = threading.Thread(target=lambda: found.append(aot.ensure_built(timeout=60.0)))
        waiter.start()
        waiter.join(timeout=1.0)
        assert waiter.is_alive() and not found  # waiting for the holder, not building
        holder.stdin.write("done\n")
        holder.stdin.flush()
        waiter.join(timeout=60.0)
        assert found == [built]
    finally:
        holder.kill()
        holder.wait()


def test_tools_compile_the_estimator_before_starting_a_node_only_when_needed(tmp_path, monkeypatch, capsys):
    from profile_pose_ros.tools.graph import prepare_kernel

    assert aot.load() is not None
    assert aot.is_current()
    prepare_kernel()  # built: nothing to say, nothing to do
    assert capsys.readouterr().out == ""
    monkeypatch.setenv("PROFILE_POSE_AOT_DIR", str(tmp_path))
    assert not aot.is_current()
    monkeypatch.setenv("PROFILE_POSE_KERNEL", "jit")
    prepare_kernel()  # the JIT was asked for: no build
    assert capsys.readouterr().out == "" and not any(tmp_path.iterdir())


def test_the_jit_caches_each_version_of_the_kernels_apart(tmp_path):
    """numba keys a function's cache on its own file: a caller's cached code would outlive an edit to a callee
    in another file. The kernels' JIT cache is one directory per fingerprint of all their sources, unless the
    user chose one."""
    code = ("import numba; from profile_pose_ros.core.compiled import caches, kernel; "
            "print(numba.config.CACHE_DIR == str(caches.jit_cache()), caches.fingerprint() in numba.config.CACHE_DIR)")
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         env={**env, "XDG_CACHE_HOME": str(tmp_path)}).stdout.split()
    assert out == ["True", "True"] and (tmp_path / "profile_pose_ros" / "jit" / caches.fingerprint()).is_dir()
    chosen = subprocess.run([sys.executable, "-c", "import numba; from profile_pose_ros.core.compiled import kernel; "
                             "print(numba.config.CACHE_DIR)"], capture_output=True, text=True, timeout=300,
                            env={**env, "NUMBA_CACHE_DIR": str(tmp_path / "mine")}).stdout.strip()
    assert chosen == str(tmp_path / "mine")
