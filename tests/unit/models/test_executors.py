"""models.executors: every backend returns fn(task) in task order; a labeling batch is bit-for-bit the
same on serial, local processes and Ray; bad names refused; Ray stays on 127.0.0.1."""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest

from models.errors import ModelInputError
from models.executors import (
    EXECUTORS,
    Executor,
    LocalProcessExecutor,
    RayExecutor,
    SerialExecutor,
    make_executor,
    worker_cached,
)

if TYPE_CHECKING:
    from tests.unit.models.hmpc.conftest import States  # solve_batch's q, qd, q_d, qd_d, qdd_d

HAVE_RAY = importlib.util.find_spec("ray") is not None  # not imported here: RayExecutor imports it
needs_ray = pytest.mark.skipif(not HAVE_RAY, reason="ray not installed (the ray extra; [all,test] installs it)")


def _square_and_pid(x: int) -> tuple[int, int]:
    return x * x, os.getpid()


def _fails_on_three(x: int) -> int:
    if x == 3:
        raise ModelInputError("task 3 refused")
    return x


def labeling_batch(rows: int = 24, seed: int = 5) -> tuple[Any, Any, States, Any]:
    # the law, the robot model, (q, qd, q_d, qd_d, qdd_d), the labeler's HMPCConfig
    """A small labeling batch: PD-law states near a moving reference, the labeler's HMPC options."""
    from models.feedback import make_law
    from models.hmpc import HMPCConfig
    from models.lmpc.labels import LABEL_HMPC_OPTIONS
    from models.robots import load_robot

    robot = load_robot("ur5_paper")
    law = make_law("pd", robot)
    rng = np.random.default_rng(seed)
    q_d = rng.uniform(-1.0, 1.0, (rows, 6))
    qd_d = rng.uniform(-0.3, 0.3, (rows, 6))
    qdd_d = rng.uniform(-0.2, 0.2, (rows, 6))
    q = q_d + rng.normal(0.0, 0.02, (rows, 6))
    qd = qd_d + rng.normal(0.0, 0.1, (rows, 6))
    return law, robot, (q, qd, q_d, qd_d, qdd_d), HMPCConfig.from_options(**LABEL_HMPC_OPTIONS)


def label(executor: Executor) -> tuple[np.ndarray, np.ndarray]:
    from models.hmpc import solve_batch

    law, robot, args, config = labeling_batch()
    return solve_batch(law, robot, *args, config=config, executor=executor, chunk_states=5)


def test_make_executor_names_and_refusals() -> None:
    assert EXECUTORS == ("serial", "local", "ray")
    assert isinstance(make_executor("serial"), SerialExecutor)
    assert isinstance(make_executor(), LocalProcessExecutor)  # local is the default
    assert make_executor("local", 3).workers == 3
    assert isinstance(make_executor("ray", 2), RayExecutor)  # nothing starts before the first map
    with pytest.raises(ModelInputError, match=r"--executor: unknown 'dask' \(known: serial, local, ray\)"):
        make_executor("dask")
    with pytest.raises(ModelInputError, match="--workers: must be >= 1, got 0"):
        make_executor("local", 0)


def test_local_processes_keep_order_and_use_other_processes() -> None:
    with LocalProcessExecutor(2) as executor:
        out = list(executor.map(_square_and_pid, list(range(9))))
    assert [r for r, _ in out] == [x * x for x in range(9)]
    assert os.getpid() not in {pid for _, pid in out}


def test_a_task_error_reaches_the_caller() -> None:
    with LocalProcessExecutor(2) as executor, pytest.raises(ModelInputError, match="task 3 refused"):
        list(executor.map(_fails_on_three, list(range(6))))


def test_worker_cached_builds_once_per_key() -> None:
    built: list[str] = []
    for key in ("a", "a", "b", "a"):

        def build(k: str = key) -> str:
            built.append(k)
            return k

        assert worker_cached(f"test-{key}", build) == key
    assert built == ["a", "b"]


def test_labeling_batch_local_equals_serial_bit_for_bit() -> None:
    serial = label(SerialExecutor())
    with LocalProcessExecutor(2) as executor:
        local = label(executor)
    np.testing.assert_array_equal(local[0], serial[0])
    np.testing.assert_array_equal(local[1], serial[1])


@needs_ray
def test_labeling_batch_ray_equals_local_bit_for_bit() -> None:
    """The Ray backend: same torques and status bits as local processes, solved in Ray's workers (the
    solver was never built in this process); a task's error reaches the caller as its own type."""
    from models import executors

    with LocalProcessExecutor(2) as executor:
        local = label(executor)
    executors._WORKER_CACHE.clear()
    with RayExecutor(2) as executor:
        ray_result = label(executor)
        # tasks must be importable by Ray's workers: a function of the package, not of this test file
        with pytest.raises(ModelInputError) as refused:
            list(executor.map(make_executor, ["serial", "dask"]))
    # the task's own error, one line, as on the other executors (not Ray's report with the traceback)
    assert type(refused.value) is ModelInputError
    assert str(refused.value) == "--executor: unknown 'dask' (known: serial, local, ray)"
    assert not executors._WORKER_CACHE
    assert ray_result[0].dtype == local[0].dtype and ray_result[0].shape == local[0].shape
    np.testing.assert_array_equal(ray_result[0], local[0])
    np.testing.assert_array_equal(ray_result[1], local[1])


RAY_PROBE = r"""
import json, os, re, subprocess
from models.executors import RayExecutor

def square(x):
    return x * x

def sockets():
    return subprocess.run(["ss", "-Htanpu"], capture_output=True, text=True, check=True).stdout.splitlines()

def descendants(root):
    parent = {}
    for entry in os.listdir("/proc"):
        try:
            with open(f"/proc/{entry}/stat") as handle:
                parent[int(entry)] = int(handle.read().rsplit(")", 1)[1].split()[1])
        except (ValueError, OSError):
            pass
    tree, grew = {root}, True
    while grew:
        grew = False
        for pid, ppid in parent.items():
            if ppid in tree and pid not in tree:
                tree.add(pid)
                grew = True
    return tree

before = set(sockets())
with RayExecutor(2) as executor:
    assert list(executor.map(square, [1, 2, 3])) == [1, 4, 9]
    tree = descendants(os.getpid())
    ours = [line for line in sockets() if {int(p) for p in re.findall(r"pid=(\d+)", line)} & tree]
new = [line for line in sockets() if line not in before]
print(json.dumps({"ours": ours, "new": new, "processes": len(tree)}))
"""

LOOPBACK_HOSTS = ("127.0.0.1", "::ffff:127.0.0.1", "::1")


def _host(address: str) -> str:
    return address.rsplit(":", 1)[0].strip("[]")


@needs_ray
@pytest.mark.skipif(shutil.which("ss") is None, reason="no ss (iproute2) here")
def test_ray_listens_and_connects_on_loopback_only() -> None:
    """While Ray runs (fresh interpreter, as the CLI starts it), every socket of its processes, listening
    or connected, is on 127.0.0.1 / ::1; and no connection to a cloud metadata server was opened."""
    out = subprocess.run([sys.executable, "-c", RAY_PROBE], capture_output=True, text=True, timeout=240)
    assert out.returncode == 0, out.stderr[-2000:]
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["processes"] > 3 and report["ours"], report  # Ray's processes and their sockets were seen
    for line in report["ours"]:
        local, peer = line.split()[4:6]
        assert _host(local) in LOOPBACK_HOSTS, line
        # a connection's peer is loopback; a listening socket's peer is ss's wildcard "<any>:*"
        assert _host(peer) in LOOPBACK_HOSTS or peer.endswith(":*"), line
    metadata = [line for line in report["new"] if "169.254.169.254" in line]
    assert not metadata, metadata


RAY_INTERRUPTED = r"""
import sys, time
from models.executors import RayExecutor
with RayExecutor(2) as executor:
    print("started", flush=True)
    try:
        list(executor.map(time.sleep, [120.0, 120.0, 120.0]))
    except KeyboardInterrupt:
        print("interrupted", flush=True)
        code = 130
sys.exit(code)
"""


def _group_members(pgid: int) -> list[str]:
    rows = subprocess.run(["ps", "-eo", "pid=,pgid=,comm="], capture_output=True, text=True, check=True).stdout
    return [row for row in rows.splitlines() if row.split()[1] == str(pgid) and row.split()[0] != str(pgid)]


@needs_ray
def test_ray_ctrl_c_on_the_process_group_shuts_down_cleanly() -> None:
    """Ctrl-C on a terminal reaches the whole process group: the driver gets KeyboardInterrupt, Ray
    shuts down in order (no crash on exit) and none of its processes is left behind."""
    import signal
    import time

    process = subprocess.Popen(
        [sys.executable, "-c", RAY_INTERRUPTED],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group, as a shell gives a foreground job
    )
    try:
        assert process.stdout is not None and process.stdout.readline().strip() == "started"
        # the tasks are running in Ray's workers: GCS, raylet, workers, all in the same group (under
        # load Ray's processes take seconds to appear: wait for them, up to 30 s)
        deadline = time.monotonic() + 30.0
        while len(_group_members(process.pid)) < 3 and time.monotonic() < deadline:
            time.sleep(0.2)
        assert len(_group_members(process.pid)) >= 3
        os.killpg(process.pid, signal.SIGINT)
        stdout, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
    assert process.returncode == 130, stderr[-2000:]
    assert "interrupted" in stdout
    time.sleep(1.0)
    assert _group_members(process.pid) == []
