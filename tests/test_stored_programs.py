"""Compiled programs stored on disk between processes (``solver._stored``)."""

from __future__ import annotations

import numpy as np
import pytest

from spdslam.factors import BetweenFactor, PriorFactor
from spdslam.geometry.se3 import from_tum
from spdslam.solver import LevenbergMarquardt, NonlinearFactorGraph, Values, X, clear_caches
from spdslam.solver._stored import StoredProgram, own_code, store_dir


@pytest.fixture
def store(tmp_path, monkeypatch):
    monkeypatch.setenv("SPDSLAM_CACHE_DIR", str(tmp_path))
    return tmp_path / "programs"


def test_a_stored_program_is_loaded_not_traced_and_gives_the_same_result(store):
    traced = []

    def f(x, y):
        traced.append(1)  # runs only while tracing
        return np.float64(2.0) * x @ y, x.sum()

    x, y = np.arange(12.0).reshape(3, 4), np.ones((4, 2))
    first = StoredProgram(f, "test f")(x, y)
    assert len(traced) == 1 and len(list(store.glob("*.bin"))) == 1
    again = StoredProgram(f, "test f")  # a new process's program: loaded from the store
    second = again(x, y)
    assert len(traced) == 1
    for a, b in zip(first, second):
        np.testing.assert_array_equal(a, b)
    again(x + 1, y)  # its compiled code is called from then on
    assert len(traced) == 1
    StoredProgram(f, "test f")(np.ones((2, 4)), y)  # other shapes: another program
    assert len(traced) == 2 and len(list(store.glob("*.bin"))) == 2
    StoredProgram(lambda a, b: f(a, b), None)(x, y)  # no key: plain jit (traced)
    assert len(traced) == 3 and len(list(store.glob("*.bin"))) == 2


def test_a_damaged_stored_program_is_rebuilt(store):
    def f(x):
        return x * 3.0

    x = np.arange(4.0)
    StoredProgram(f, "test g")(x)
    (path,) = store.glob("*.bin")
    path.write_bytes(b"not a program")
    np.testing.assert_array_equal(StoredProgram(f, "test g")(x), 3 * x)
    assert path.read_bytes() != b"not a program"


def test_the_store_is_off_with_the_cache(monkeypatch):
    monkeypatch.setenv("SPDSLAM_CACHE_DIR", "off")
    assert store_dir() is None


def test_only_spdslams_own_module_level_code_is_stored():
    assert own_code(BetweenFactor.residual, PriorFactor.residual, None)
    assert not own_code(lambda x: x)
    assert not own_code(np.sum)

    def local(x):
        return x

    assert not own_code(local)
    from spdslam.factors import Huber
    from spdslam.geometry import Ellipsoid

    assert own_code(Huber, Ellipsoid)  # classes of the covered modules

    class Kernel(Huber):  # a user's kernel: its code is not in the key
        pass

    assert not own_code(Kernel)


def test_an_optimisation_in_a_new_process_traces_no_builtin_program(store, monkeypatch):
    """The general path's programs are stored (with the closed forms turned off: the pose
    factors' need no program at all)."""
    from spdslam.solver import _problem, closed_forms

    poses = [from_tum([0.1 * i, 0, 0, 0, 0, 0, 1]) for i in range(5)]
    graph = NonlinearFactorGraph([PriorFactor(X(0), poses[0], sigma=0.1)] + [
        BetweenFactor(X(i), X(i + 1), poses[i].inverse() @ poses[i + 1], sigma=0.1) for i in range(4)])
    values = Values({X(i): from_tum([0.1 * i + 0.01 * i**2, 0.02, 0, 0, 0, 0, 1]) for i in range(5)})
    with closed_forms(False):
        first = LevenbergMarquardt().optimize(graph, values)
        assert list(store.glob("*.bin"))
        clear_caches()  # as a new process: no program in memory
        traced = []
        group_map = _problem._group_map
        monkeypatch.setattr(_problem, "_group_map", lambda *a: traced.append(1) or group_map(*a))
        second = LevenbergMarquardt().optimize(graph, values)
        assert traced == []
        assert second.final_cost == first.final_cost
        for i in range(5):
            np.testing.assert_array_equal(second.values[X(i)].wxyz_xyz, first.values[X(i)].wxyz_xyz)
        clear_caches()
        monkeypatch.setenv("SPDSLAM_CACHE_DIR", "off")  # the check can fail: without the store it traces
        LevenbergMarquardt().optimize(graph, values)
        assert traced


def test_a_pose_graph_traces_no_group_program_at_all(store, monkeypatch):
    """With the closed forms (the default), priors and odometry are linearised in NumPy: not
    one group program is traced, even with an empty store."""
    from spdslam.solver import _problem

    poses = [from_tum([0.1 * i, 0, 0, 0, 0, 0, 1]) for i in range(5)]
    graph = NonlinearFactorGraph([PriorFactor(X(0), poses[0], sigma=0.1)] + [
        BetweenFactor(X(i), X(i + 1), poses[i].inverse() @ poses[i + 1], sigma=0.1) for i in range(4)])
    values = Values({X(i): from_tum([0.1 * i + 0.01 * i**2, 0.02, 0, 0, 0, 0, 1]) for i in range(5)})
    clear_caches()
    traced = []
    group_map = _problem._group_map
    monkeypatch.setattr(_problem, "_group_map", lambda *a: traced.append(1) or group_map(*a))
    result = LevenbergMarquardt().optimize(graph, values)
    assert traced == []
    assert result.final_cost < 1e-12


def test_a_box_problem_runs_no_xla_program_at_all(monkeypatch):
    """Building and optimising poses and an ellipsoid under box factors and odometry (the
    closed forms) instantiates no XLA program, not even one loaded from the cache: the host
    arrays go to the device by transfer (``jnp.asarray`` of one runs a program per shape, and
    with an empty cache compiles it)."""
    import jax
    import jax._src.compiler as compiler

    from spdslam.factors import Cauchy, InverseBoxFactor
    from spdslam.geometry import Camera, Ellipsoid, look_at, project_box
    from spdslam.solver import L

    cam = Camera(fx=520.0, fy=520.0, cx=320.0, cy=240.0, width=640.0, height=480.0)
    rng = np.random.default_rng(0)
    lm = Ellipsoid.from_axes(np.eye(3), np.array([0.0, 0.0, 0.5]), np.array([0.3, 0.2, 0.1]))
    poses = [look_at(np.array([3.0 * np.cos(a), 3.0 * np.sin(a), 1.5]), np.array([0.0, 0.0, 0.5]))
             for a in np.linspace(0.0, 1.2, 8)]
    boxes = np.array([np.asarray(project_box(lm, T, cam)) for T in poses]) + rng.normal(scale=1.0, size=(8, 4))
    graph = NonlinearFactorGraph([PriorFactor(X(0), poses[0], sigma=0.01)] + [
        BetweenFactor(X(i), X(i + 1), poses[i].inverse() @ poses[i + 1], sigma=0.05) for i in range(7)])
    graph.add(InverseBoxFactor.many([X(i) for i in range(8)], [L(0)] * 8, boxes, cam, sigma=2.0, robust=Cauchy(1.0)))
    values = Values({X(i): poses[i] for i in range(8)})
    values.insert(L(0), Ellipsoid.from_axes(np.eye(3), np.array([0.05, 0.0, 0.45]), np.array([0.25, 0.25, 0.12])))
    jax.clear_caches()  # as a new process
    programs = []
    instantiate = compiler.compile_or_get_cached
    monkeypatch.setattr(compiler, "compile_or_get_cached", lambda *a, **k: programs.append(1) or instantiate(*a, **k))
    result = LevenbergMarquardt().optimize(graph, values)
    assert result.final_cost < 0.5 * result.initial_cost
    assert programs == []
    jax.numpy.asarray(np.arange(3.0) + 1e-3)  # the count sees a program when one runs
    assert programs


_PROCESS = """
import sys
import numpy as np
import jax.numpy as jnp
from spdslam.solver import StoredProgram

def solve(a, b):  # LAPACK kernels (getrf, syevd): a loaded executable must find them registered
    return jnp.linalg.solve(a, b), jnp.linalg.eigh(a)[0]

a = np.eye(3) * 2.0 + 0.1
x, w = StoredProgram(solve, "test lapack")(a, np.arange(3.0))
print(repr((x.tolist(), w.tolist())))
"""


def test_a_stored_program_that_calls_lapack_runs_in_a_new_process(store):
    import os
    import subprocess
    import sys

    env = dict(os.environ, SPDSLAM_CACHE_DIR=str(store.parent))
    first = subprocess.run([sys.executable, "-c", _PROCESS], env=env, capture_output=True, text=True)
    assert first.returncode == 0, first.stderr
    assert len(list(store.glob("*.bin"))) == 1
    second = subprocess.run([sys.executable, "-c", _PROCESS], env=env, capture_output=True, text=True)
    assert second.returncode == 0, second.stderr[-2000:]  # was a segmentation fault (exit -11)
    assert second.stdout == first.stdout


def test_a_stored_program_whose_first_run_never_ended_is_rebuilt(store):
    def f(x):
        return x + 1.0

    x = np.arange(3.0)
    StoredProgram(f, "test h")(x)
    (path,) = store.glob("*.bin")
    import os
    import subprocess

    gone = subprocess.Popen(["true"])
    gone.wait()  # a process id that no longer runs
    running = path.with_suffix(f".{os.getppid()}.trying")  # another process running it now
    running.touch()
    before = path.stat().st_ino, path.stat().st_mtime_ns
    np.testing.assert_array_equal(StoredProgram(f, "test h")(x), x + 1)
    assert (path.stat().st_ino, path.stat().st_mtime_ns) == before  # loaded: no sign of a crash
    path.with_suffix(f".{gone.pid}.trying").touch()  # as a process that crashed in its first run leaves it
    np.testing.assert_array_equal(StoredProgram(f, "test h")(x), x + 1)
    assert path.is_file() and not path.with_suffix(f".{gone.pid}.trying").exists() and running.exists()
    assert (path.stat().st_ino, path.stat().st_mtime_ns) != before  # compiled and stored anew


_SERVED = """
import sys
import numpy as np
import jax.numpy as jnp
from spdslam.solver import StoredProgram, enable_compilation_cache

enable_compilation_cache()  # JAX's persistent cache, in SPDSLAM_CACHE_DIR

def f(a, b):
    return jnp.linalg.solve(a, b) * 2.0

print(StoredProgram(f, "test served")(np.eye(3) * 2.0 + 0.1, np.arange(3.0)).tolist())
"""


def test_a_build_is_neither_served_nor_kept_by_the_persistent_cache(store):
    import os
    import subprocess
    import sys

    env = dict(os.environ, SPDSLAM_CACHE_DIR=str(store.parent))

    def run():
        out = subprocess.run([sys.executable, "-c", _SERVED], env=env, capture_output=True, text=True)
        assert out.returncode == 0, out.stderr[-2000:]
        return out.stdout

    first = run()  # compiled and stored; not written to JAX's persistent cache
    (path,) = store.glob("*.bin")
    path.unlink()  # as after an edit of spdslam that leaves the program unchanged
    # compiled afresh and stored again (an executable the cache had served would lack its
    # machine code: a later process running it fails)
    assert run() == first
    assert [p.name for p in store.glob("*.bin")] == [path.name]
    assert run() == first  # loaded and run
