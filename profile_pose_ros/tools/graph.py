"""Several package executables, each its own process on one private DDS domain, plus a client node here
to watch them: what the checks, the experiment and the soak run against."""
from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import time
from pathlib import Path

import yaml

from ..nodes.direct_input import DirectInput, ServedDirectly, serve_ready
from ..resources import PACKAGE, ament_prefix
from . import processes

MODULES = {
    "sim_cell": "profile_pose_ros.nodes.sim_cell",
    "profiler_driver": "profile_pose_ros.nodes.profiler_driver",
    "pose_estimator": "profile_pose_ros.nodes.pose_estimator",
    "pd_compensator": "profile_pose_ros.nodes.pd_compensator",
    "motoplus_bridge": "profile_pose_ros.nodes.motoplus_bridge",
    "cell_container": "profile_pose_ros.nodes.cell_container",
    "profiler_estimator": "profile_pose_ros.nodes.profiler_estimator",
    "compensator_bridge": "profile_pose_ros.nodes.compensator_bridge",
    "bag_recorder": "profile_pose_ros.nodes.bag_recorder",
    "bag_player": "profile_pose_ros.nodes.bag_player",
}


CLIENT_CPU = "(this client)"  # Graph.cpu_seconds' key for the measuring process itself


def cpu_percent(before: dict[str, float], after: dict[str, float], wall_s: float) -> dict[str, float]:
    """Each process's share of one core (%) between two Graph.cpu_seconds() readings wall_s apart."""
    return {name: 100.0 * (used - before[name]) / wall_s for name, used in after.items() if name in before}


def free_ports(count: int) -> list[int]:
    """`count` different TCP ports free on 127.0.0.1 right now (the OS picks them). All are held until every one
    is picked: a port closed before the next is asked for can be handed out again, and a cell whose profiler
    and robot controller were given one port fails to start (seen: the controller's "cannot listen")."""
    with contextlib.ExitStack() as held:
        sockets = [held.enter_context(socket.socket()) for _ in range(count)]
        for s in sockets:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in sockets]


def free_port() -> int:
    """A TCP port free on 127.0.0.1 right now (the OS picks it)."""
    return free_ports(1)[0]


def ros_params(values: dict) -> list[str]:
    args = []
    for name, value in values.items():
        if isinstance(value, bool):
            text = "true" if value else "false"
        elif isinstance(value, (list, tuple)):
            text = "[" + ",".join(repr(v) if isinstance(v, str) else str(v) for v in value) + "]"
        elif isinstance(value, str):  # YAML-quoted: "" or "true" must stay strings
            text = "'" + value.replace("'", "''") + "'"
        else:
            text = str(value)
        args += ["-p", f"{name}:={text}"]
    return args


def launcher(executable: str) -> list[str]:
    """The installed executable itself where the ament index knows the package (the file `ros2 run
    profile_pose_ros <exe>` would run), else the venv's console script (or `python -m`). Never the
    `ros2 run` wrapper: it ignores SIGINT and waits, so a stop would reach the wrapper and not the node,
    and the node would outlive the bringup."""
    installed = installed_executable(executable)
    return [str(installed)] if installed is not None else processes.executable(executable, MODULES[executable])


def installed_executable(executable: str) -> Path | None:
    """<prefix>/lib/profile_pose_ros/<exe> of the package the ament index (AMENT_PREFIX_PATH) finds."""
    prefix = ament_prefix()
    path = None if prefix is None else prefix / "lib" / PACKAGE / executable
    return path if path is not None and os.access(path, os.X_OK) else None


ESTIMATING = ("pose_estimator", "cell_container", "profiler_estimator")  # executables that load the compiled estimator
_build_failed = False  # this process tried to build the estimator and could not: do not try at every start


def prepare_kernel() -> None:
    """Build this machine's compiled estimator before an estimator process starts, saying so: the first
    time, that takes a minute or more, and a node compiling at start-up would look to the tool like a
    graph that never sends poses."""
    global _build_failed
    from ..core.compiled import aot, loader

    if _build_failed or not loader.will_compile():
        return
    print("[setup] compiling the estimator for this machine (once, about a minute)", flush=True)
    started = time.monotonic()
    ready = aot.ensure_built() is not None
    _build_failed = not ready
    print(f"[setup] estimator {'compiled' if ready else 'could not be compiled here; the JIT will be used'}"
          f" in {time.monotonic() - started:.0f} s", flush=True)


REPLY_WAIT_S = 1.0  # how long first_answered waits for a reply before it sends the request again


def first_answered(send, spin_until, deadline: float, wait: float = REPLY_WAIT_S):
    """The first of the futures send() returns that is done, sending again every `wait` s until the monotonic
    `deadline`; None if none is answered by then. For a request that changes nothing, whose reply may be lost
    (spin_until(condition, timeout) serves the replies)."""
    futures = []
    while True:
        futures.append(send())
        spin_until(lambda: any(f.done() for f in futures), max(0.0, min(wait, deadline - time.monotonic())))
        answered = next((f for f in futures if f.done()), None)
        if answered is not None or time.monotonic() >= deadline:
            return answered


def parameter_client(node, target: str, spin_until, timeout: float):
    """An AsyncParameterClient on `node` for the node named `target` whose replies reach it, or RuntimeError.
    wait_for_services sees the request's path only: a reply can still be dropped while the target's reply writer
    has not matched this client's reader (Fast DDS drops it after 100 ms; ros2/ros2#1253). An empty request
    changes nothing, so it is sent again until one is answered, and a caller's real request then goes out once
    (sent twice, sim_cell's clock would restart and count its triggers again)."""
    from rclpy.parameter_client import AsyncParameterClient

    deadline = time.monotonic() + timeout
    client = AsyncParameterClient(node, target)
    if not client.wait_for_services(timeout_sec=timeout):
        raise RuntimeError(f"{target}'s parameter services are not available")
    if first_answered(lambda: client.set_parameters([]), spin_until, deadline) is None:
        raise RuntimeError(f"{target} did not answer set_parameters")
    return client


class Graph:
    """Processes are closed in the reverse of their start order: start the cell first and the bridge
    last, so that the bridge stops (and sends STOP) first."""

    def __init__(self, log_dir: Path, domain_id: int | None = None, client_name: str = "graph_client",
                 namespace: str = "", params_file: Path | list[Path] | None = None) -> None:
        """params_file: one parameter file or several (a later one overrides an earlier one, e.g. a cell's
        file, then its calibration) that every node is started with; None: each node's `-p` values only."""
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        self.namespace = namespace.strip("/")
        self.params_files = [params_file] if isinstance(params_file, (str, Path)) else list(params_file or [])
        self._launcher: dict[str, list[str]] = {}
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.domain_id = domain_id if domain_id is not None else processes.fresh_domain_id()
        self.processes: dict[str, subprocess.Popen] = {}
        self.commands: dict[str, list[str]] = {}  # name -> how it was started, for restart()
        self.restarts: dict[str, int] = {}
        self.rclpy = rclpy
        self.context = Context()
        rclpy.init(context=self.context, domain_id=self.domain_id)
        self.node = rclpy.create_node(client_name, context=self.context,
                                      namespace="/" + self.namespace if self.namespace else None)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.direct_input = DirectInput(None, self.context)  # the high-rate topics (subscribe_fast)
        self._served_here = ServedDirectly()
        self._parameter_clients: dict = {}
        self.diagnostics: dict[str, dict] = {}  # status name -> its values, the newest of each node
        self.messages: dict[str, str] = {}  # status name -> its message, the newest
        self.received: dict[str, float] = {}  # status name -> time.monotonic() its newest report came
        self.diagnostics_listeners: list = []  # callables(status name, values): every report, not just the newest
        from diagnostic_msgs.msg import DiagnosticArray

        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 100)

    def _on_diagnostics(self, msg) -> None:
        for status in msg.status:
            values = self.diagnostics[status.name] = {kv.key: kv.value for kv in status.values}
            self.messages[status.name] = status.message
            self.received[status.name] = time.monotonic()
            for listener in self.diagnostics_listeners:
                listener(status.name, values)

    def is_from(self, status: str, node: str) -> bool:
        """Whether a /diagnostics status name is that of `node` of this graph's namespace."""
        return status.startswith(f"{self.namespace}/{node}:" if self.namespace else f"{node}:")

    def reported(self, node: str) -> bool:
        """Whether `node` of this graph's namespace has published /diagnostics."""
        return any(self.is_from(name, node) for name in self.diagnostics)

    def forget(self, node: str) -> None:
        """Drop what `node` last reported, so that only its next report counts (e.g. after a restart)."""
        for name in [n for n in self.diagnostics if self.is_from(n, node)]:
            del self.diagnostics[name]
            self.received.pop(name, None)

    def diagnostic(self, node: str, key: str, default: str = "") -> str:
        """A value from the newest /diagnostics of `node` of this graph's namespace."""
        for name, values in self.diagnostics.items():
            if self.is_from(name, node):
                return values.get(key, default)
        return default

    def reported_at(self, node: str) -> float:
        """time.monotonic() when the newest /diagnostics of `node` came (nan if none): the time its counts are
        from, to within the transport's delay."""
        return next((t for name, t in self.received.items() if self.is_from(name, node)), float("nan"))

    def diagnostics_message(self, node: str) -> str:
        """The message of the newest /diagnostics status of `node` of this graph's namespace."""
        return next((m for name, m in self.messages.items() if self.is_from(name, node)), "")

    def cpu_seconds(self) -> dict[str, float]:
        """CPU time (user + system) each node process has used so far, and this client's own under
        CLIENT_CPU: differences over a window give each one's share of the machine."""
        out = {}
        for name, process in self.processes.items():
            try:
                out[name] = processes.cpu_seconds(process.pid)
            except (FileNotFoundError, ProcessLookupError):  # it died; spin_until reports that
                out[name] = float("nan")
        out[CLIENT_CPU] = time.process_time()
        return out

    def start(self, executable: str, params: dict | None = None, name: str | None = None) -> subprocess.Popen:
        name = name or executable
        if executable in ESTIMATING:
            prepare_kernel()
        command = self._ros_command(executable)
        if not self.params_files:
            command += ros_params(params or {})
        else:  # a file's node block beats `-p`; a later file beats an earlier one
            command += self._params_file_arguments()
            if params:
                overrides = self.log_dir / f"{name}.overrides.yaml"
                overrides.write_text(yaml.safe_dump({f"/**/{executable}": {"ros__parameters": dict(params)}}))
                command += ["--params-file", str(overrides)]
        with open(self.log_dir / "params.yaml", "a") as f:  # what each node was given, for a replay
            f.write(yaml.safe_dump({executable: {"ros__parameters": dict(params or {})}}, sort_keys=False))
        return self._record_and_launch(name, command)

    def start_composed(self, node_params: dict[str, dict], name: str = "cell_container") -> subprocess.Popen:
        """A container of several nodes (cell_container: the loop's four; profiler_estimator: driver and
        estimator; compensator_bridge), each node with its own parameters: a file with one block per node name,
        since `-p` would give every node the same value (`port` is the driver's profiler port and the bridge's
        controller port)."""
        prepare_kernel()
        command = self._ros_command(name)
        command += self._params_file_arguments()
        blocks = {f"/**/{node}": {"ros__parameters": dict(params)} for node, params in node_params.items()}
        (self.log_dir / f"{name}.params.yaml").write_text(yaml.safe_dump(blocks, sort_keys=False))
        command += ["--params-file", str(self.log_dir / f"{name}.params.yaml")]
        with open(self.log_dir / "params.yaml", "a") as f:
            f.write(yaml.safe_dump({node: {"ros__parameters": dict(params)} for node, params in node_params.items()},
                                   sort_keys=False))
        return self._record_and_launch(name, command)

    def start_nodes(self, node_params: dict[str, dict], container: str | None = None) -> None:
        """Several nodes, each its own process, or all of them in one `container` process (start_composed)."""
        if container is not None:
            self.start_composed(node_params, name=container)
            return
        for executable, params in node_params.items():
            self.start(executable, params)

    def _params_file_arguments(self) -> list[str]:
        return [argument for path in self.params_files for argument in ("--params-file", str(path))]

    def _ros_command(self, executable: str) -> list[str]:
        """How to run `executable` (launcher()), up to its ROS arguments: the namespace, if any."""
        if executable not in self._launcher:
            self._launcher[executable] = launcher(executable)
        command = [*self._launcher[executable], "--ros-args"]
        if self.namespace:
            command += ["-r", f"__ns:=/{self.namespace}"]
        return command

    def _record_and_launch(self, name: str, command: list[str]) -> subprocess.Popen:
        with open(self.log_dir / "commands.txt", "a") as f:
            f.write(f"ROS_DOMAIN_ID={self.domain_id} {' '.join(command)}\n")
        self.commands[name] = command
        return self._launch(name)

    def _launch(self, name: str) -> subprocess.Popen:
        count = self.restarts.get(name, 0)
        log = self.log_dir / (f"{name}.log" if not count else f"{name}.restart{count}.log")
        process = processes.start(self.commands[name], self.domain_id, log)
        self.processes[name] = process
        return process

    def stop(self, name: str) -> int:
        return processes.stop(self.processes.pop(name))

    def kill(self, name: str, signum: int = signal.SIGKILL, timeout: float = 10.0) -> int:
        """Fault injection: signal a node and wait for it to end (it is no longer watched for dying)."""
        process = self.processes.pop(name)
        process.send_signal(signum)
        try:
            process.wait(timeout)
        finally:
            processes.stop(process)
        return process.returncode

    def restart(self, name: str) -> subprocess.Popen:
        """Start a killed node again with the very command it was first started with."""
        if name in self.processes:
            raise RuntimeError(f"{name} is still running")
        self.restarts[name] = self.restarts.get(name, 0) + 1
        return self._launch(name)

    def subscribe_fast(self, msg_type, topic: str, callback, depth: int = 1000):
        """A subscription for a high-rate topic, taken directly (nodes/direct_input.py): through the executor,
        the client's per-message overhead at 250 Hz took CPU the graph under test needed."""
        subscription = self.node.create_subscription(msg_type, topic, callback, depth,
                                                     callback_group=self._served_here)
        self.direct_input.add(subscription, callback)
        return subscription

    def unsubscribe_fast(self, subscription) -> None:
        self.direct_input.remove(subscription)
        self.node.destroy_subscription(subscription)

    def spin_until(self, condition, timeout: float, housekeeping_period: float = 0.01) -> bool:
        """Spin the client until condition() or the deadline; a node process that died is an error. The
        fast subscriptions are served as their messages come, everything else every housekeeping_period."""
        deadline = time.monotonic() + timeout
        due = time.monotonic()
        while not condition() and time.monotonic() < deadline:
            if time.monotonic() >= due:
                for name, process in self.processes.items():
                    if process.poll() is not None:
                        raise RuntimeError(f"{name} exited with {process.returncode}; see {self.log_dir / name}.log")
                serve_ready(self.executor)
                due = time.monotonic() + housekeeping_period
            self.direct_input.pump(min(due, deadline) - time.monotonic())
        return bool(condition())

    def set_parameters(self, node_name: str, values: dict, timeout: float = 10.0) -> None:
        """Set parameters of a running node through its service; raises if refused or unanswered."""
        from rclpy.parameter import Parameter

        if node_name not in self._parameter_clients:
            self._parameter_clients[node_name] = parameter_client(self.node, node_name, self.spin_until, timeout)
        client = self._parameter_clients[node_name]
        future = client.set_parameters([Parameter(k, value=v) for k, v in values.items()])
        self.spin_until(future.done, timeout)
        if not future.done():
            raise RuntimeError(f"{node_name} did not answer set_parameters")
        refused = [r.reason for r in future.result().results if not r.successful]
        if refused:
            raise RuntimeError(f"{node_name} refused {values}: {refused}")

    def close(self) -> None:
        for name in reversed(list(self.processes)):  # consumers first, the cell last
            self.stop(name)
        self.executor.shutdown()
        self.node.destroy_node()
        self.rclpy.shutdown(context=self.context)
