"""Running one endo3d node as an OS process: init, spin, clean shutdown.

Every console script of a node calls :func:`run_node`. It logs the DDS
settings the process actually got (domain, discovery range, RMW), warns when
discovery is not restricted (the default Fast DDS discovery multicasts on
every interface), gives the process Fast DDS's large-frame transport before
``rclpy.init`` unless the user chose one (:mod:`endo_io.dds_transport`), and
turns SIGINT and SIGTERM into an orderly shutdown so that nodes holding
files (the recorder) can finalise them.

SIGINT raises no KeyboardInterrupt in a node (:func:`sigint_shuts_down_only`):
Python's default handler raises it at whatever bytecode runs, inside a
callback, a publish or the MCAP writer (one landing after a chunk's
``os.write`` and before its byte count left a recording no reader opened).
Under :func:`run_node` SIGINT only shuts the context down: the callback that
runs finishes, ``spin()`` returns, and the node's ``close()`` runs; a second
SIGINT while closing changes nothing. Only while the node is still being
created (the SFS node compiling its kernels for minutes on a fresh install)
does a second SIGINT abandon the start-up with a KeyboardInterrupt, which
:func:`run_node` turns into exit 0.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import re
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import FrameType

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.signals import (
    SignalHandlerOptions,
    get_current_signal_handlers_options,
    uninstall_signal_handlers,
)
from rclpy.utilities import get_rmw_implementation_identifier

from endo_io.cli import report_error
from endo_io.dds_transport import TransportChoice, configure_large_frames
from endo_io.errors import Endo3dError, ParameterValidationError, RosArgumentsError
from endo_io.shm_ports import CHECK_PERIOD_S as SHM_PORT_CHECK_PERIOD_S
from endo_io.shm_ports import SharedMemoryPortLostError, SharedMemoryPortWatch, reserve_ports

#: At most this many restarts for a lost shared-memory port within RESTART_WINDOW_S;
#: past them the node stays up and logs the loss (a port lost again and again is not
#: the race endo_io.shm_ports describes, and restarting would only lose state).
MAX_RESTARTS = 3
RESTART_WINDOW_S = 60.0


@dataclass(frozen=True)
class DdsEnvironment:
    """The DDS settings of this process, as rclpy and the environment give them."""

    domain_id: int
    discovery_range: str
    static_peers: str
    rmw_implementation: str
    transport: str = ""

    @property
    def loopback_only(self) -> bool:
        """True when discovery cannot leave this machine."""
        return self.discovery_range in ("LOCALHOST", "OFF")


#: What :func:`prepare_transport` chose for this process (None before it ran).
_transport: TransportChoice | None = None


def prepare_transport() -> TransportChoice:
    """Configure this process's Fast DDS transport; call before ``rclpy.init``.

    The first call decides (see :func:`endo_io.dds_transport.configure_large_frames`);
    later calls return that choice.
    """
    global _transport
    if _transport is None:
        _transport = configure_large_frames()
    return _transport


def dds_environment(node: Node) -> DdsEnvironment:
    """Read the DDS settings that ``node``'s context was created with."""
    return DdsEnvironment(
        domain_id=int(node.context.get_domain_id()),
        discovery_range=os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE", "SYSTEM_DEFAULT"),
        static_peers=os.environ.get("ROS_STATIC_PEERS", ""),
        rmw_implementation=get_rmw_implementation_identifier(),
        transport=_transport.description if _transport is not None else "",
    )


def log_dds_environment(node: Node) -> DdsEnvironment:
    """Log the DDS settings once at start-up; warn when discovery may leave the host."""
    env = dds_environment(node)
    text = (
        f"DDS: domain {env.domain_id}, discovery range {env.discovery_range}, "
        f"rmw {env.rmw_implementation}"
        + (f"; {env.transport}" if env.transport else "")
    )
    if env.loopback_only:
        node.get_logger().info(text)
    else:
        node.get_logger().warning(
            text + " (discovery may multicast on every interface; set "
            "ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST to keep traffic on this machine)"
        )
    return env


#: Parameters every rclpy node declares by itself; --help lists the node's own.
_RCLPY_PARAMETERS = frozenset({"use_sim_time", "start_type_description_service"})


def describe_parameters(node: Node) -> str:
    """One line per declared parameter: name, default, range or choices, description.

    Ranges come from the descriptor's numeric range, choices from its
    ``additional_constraints`` (``endo_io.parameters`` fills both from the
    node's table); read-only parameters say so.
    """
    lines = []
    for name in sorted(node._parameters):
        if name in _RCLPY_PARAMETERS or name.startswith("qos_overrides."):
            continue
        descriptor = node.describe_parameter(name)
        value = node.get_parameter(name).value
        notes = ""
        for r in (*descriptor.floating_point_range, *descriptor.integer_range):
            notes = f" [{r.from_value}, {r.to_value}]"
        if descriptor.additional_constraints and not notes:
            notes = f", {descriptor.additional_constraints}"
        if descriptor.read_only:
            notes += ", read-only"
        text = descriptor.description or ""
        lines.append(f"  {name} (default {value!r}{notes}): {text}")
    return "\n".join(lines)


_describing: contextvars.ContextVar[bool] = contextvars.ContextVar("describing", default=False)


def describing_only() -> bool:
    """True while ``--help`` creates a node only to list its parameters.

    A node whose start-up does slow work that a description does not need
    (the SFS node loads or compiles its kernels) skips that work then.
    """
    return _describing.get()


def print_node_help(factory: Callable[[], Node], argv: Sequence[str]) -> int:
    """``--help`` of a node executable: create the node once, print its parameters."""
    program = _program(argv)
    prepare_transport()
    rclpy.init(args=[program])
    try:
        token = _describing.set(True)
        try:
            node = factory()
        finally:
            _describing.reset(token)
        doc = (sys.modules[type(node).__module__].__doc__ or "").strip().split("\n\n")[0]
        print(f"usage: {program} [--ros-args [-p NAME:=VALUE] [-r FROM:=TO] ...]\n")
        if doc:
            print(doc + "\n")
        print(f"node {node.get_fully_qualified_name()}, parameters:")
        print(describe_parameters(node))
        close = getattr(node, "close", None)
        if callable(close):
            close()
        node.destroy_node()
    finally:
        rclpy.try_shutdown()
    return 0


class _SigintShutdown:
    """Python's SIGINT handler under :func:`sigint_shuts_down_only`.

    The handler only wakes a watcher thread started with it, which shuts the
    context down: starting a thread from the handler would take Python's
    thread-registry lock, which the interrupted main thread may hold (inside
    ``Thread.start``, ``threading.enumerate``, an executor's ``submit``), and
    deadlock; waking an event the main thread never otherwise touches cannot.

    Attributes:
        starting: True while the node is being created; a second SIGINT then
            raises KeyboardInterrupt (the start-up is abandoned).
        received: SIGINTs seen since :func:`sigint_shuts_down_only` installed it.
    """

    def __init__(self) -> None:
        self.starting = False
        self.received = 0
        self._wake = threading.Event()
        self._closed = False
        self._watcher = threading.Thread(target=self._watch, name="sigint-shutdown", daemon=True)
        self._watcher.start()

    def __call__(self, signum: int, frame: FrameType | None) -> None:
        """Have the watcher shut the default context down; raise nothing.

        rclpy's own handler, which ``rclpy.init`` chains before this one, wakes
        the executor and shuts the context down from its signal thread; it did
        not in a CI worker whose earlier tests had left rclpy's handlers in
        some other state (the context stayed valid for 10 s, twice), so this
        part does it too, from the watcher: here, in the main thread, the
        shutdown could wait for a lock that the interrupted code holds. A
        second shutdown is a no-op.
        """
        self.received += 1
        if self.starting and self.received > 1:
            raise KeyboardInterrupt
        self._wake.set()

    def _watch(self) -> None:
        while True:
            self._wake.wait()
            self._wake.clear()
            if self._closed:
                return
            _try_shutdown_quietly()

    def close(self) -> None:
        """Stop the watcher (the handler is no longer installed)."""
        self._closed = True
        self._wake.set()
        self._watcher.join(timeout=5.0)


def _try_shutdown_quietly() -> None:
    # rclpy's signal thread may shut the context down between try_shutdown's
    # check and its call: that error is the shutdown already done.
    with contextlib.suppress(RuntimeError):
        rclpy.try_shutdown()


def _uninstall_rclpy_signal_handlers() -> None:
    # rclpy.try_shutdown leaves them installed, and rclpy.init does not install
    # them again over a handler set since: SIGINT would then not shut it down.
    if get_current_signal_handlers_options() != SignalHandlerOptions.NO:
        uninstall_signal_handlers()


@contextlib.contextmanager
def sigint_shuts_down_only() -> Iterator[_SigintShutdown | None]:
    """While inside, SIGINT shuts rclpy's default context down and raises no KeyboardInterrupt.

    :func:`run_node` runs every node inside. ``rclpy.init``, called inside,
    installs rclpy's handler over this one and chains to it: rclpy's wakes
    ``spin()`` and shuts the context down, and this one shuts it down as well,
    so SIGINT ends ``spin()`` even where rclpy's is not the handler the kernel
    calls. SIGTERM (rclpy's handler) and SIGKILL still end the process.
    Outside the main thread, where no handler can be set, nothing changes
    (yields None).

    Yields:
        The handler (:class:`_SigintShutdown`: its ``starting`` flag lets a
        second SIGINT abandon a start-up), or None outside the main thread.
    """
    if threading.current_thread() is not threading.main_thread():
        yield None
        return
    _uninstall_rclpy_signal_handlers()  # an earlier rclpy.init's, in this process
    handler = _SigintShutdown()
    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield handler
    finally:
        _uninstall_rclpy_signal_handlers()  # so that a later rclpy.init installs them again
        signal.signal(signal.SIGINT, previous)
        handler.close()


def run_node(factory: Callable[[], Node], args: Sequence[str] | None = None, *,
             restart_on_lost_port: bool = False) -> int:
    """Create a node with ``factory`` and spin it until SIGINT or SIGTERM.

    ``args`` are the ROS arguments (``--ros-args ...``); ``sys.argv`` by default.
    Returns the process exit code: the node's ``exit_code`` attribute when it
    has one (a replay that hit a damaged bag sets it), else 0. A node that
    cannot start on its configuration (an :class:`Endo3dError` from
    ``factory``: a parameter out of range, a calibration file that does not
    load) gives one line on stderr naming the cause and exit code 2, never a
    traceback; so do ROS arguments that rcl refuses (a ``--params-file`` that
    does not parse, a malformed remap; rcl also logs its own ``[ERROR]``
    line before it). SIGINT raises no KeyboardInterrupt in the node (see the
    module docstring): the callback it lands in finishes and ``close()`` runs.
    When Fast DDS loses the node's shared-memory receiving port
    (:mod:`endo_io.shm_ports`: matched on every topic, it would hear only
    the publishers that had the old port open), one line says so; with
    ``restart_on_lost_port`` (the processing nodes, whose state a new start
    rebuilds) the node is then created again, with a new participant, in
    this process. Without it (a recorder, whose file must not start over; a
    replay) the line is logged as an error and the node goes on.
    """
    argv = list(sys.argv if args is None else args)
    ours, _ = split_ros_args(argv)
    if "-h" in ours or "--help" in ours:
        return print_node_help(factory, argv)
    restarts: list[float] = []  # when the node was created again, monotonic seconds
    with sigint_shuts_down_only() as sigint:
        while True:
            now = time.monotonic()
            restarts = [t for t in restarts if now - t < RESTART_WINDOW_S]
            restart = restart_on_lost_port and len(restarts) < MAX_RESTARTS
            if restart_on_lost_port and not restart:
                print(f"{_program(argv)}: {len(restarts)} restarts within {RESTART_WINDOW_S:g} s "
                      "for a lost shared-memory port: no more restarts (a lost port is "
                      "logged as an error)", file=sys.stderr, flush=True)
            try:
                return _run_node(factory, argv, sigint, restart)
            except SharedMemoryPortLostError as error:
                # the node starts over (a new DDS participant, its state and
                # counters anew), as a respawn would, without leaving the
                # process, on other ports than the lost ones (see reserve_ports)
                held = reserve_ports(error.ports)
                unheld = sorted(set(error.ports) - set(held))
                note = (f" (port {', '.join(map(str, unheld))} could not be held: the new "
                        "participant may take it again)" if unheld else "")
                print(f"{_program(argv)}: {error}; restarting the node's DDS participant{note}",
                      file=sys.stderr, flush=True)
                restarts.append(time.monotonic())


def _run_node(factory: Callable[[], Node], argv: list[str],
              sigint: _SigintShutdown | None, restart_on_lost_port: bool) -> int:
    program = _program(argv)
    # rclpy's default signal handlers cover SIGINT and SIGTERM: both shut the
    # context down, spin() returns, and the node's close() still runs below.
    prepare_transport()
    try:
        rclpy.init(args=argv)
    except _rclpy.RCLError as error:  # ROS arguments rcl refuses: a --params-file, a remap
        print(f"{program}: {_refused_arguments(error)}", file=sys.stderr)
        return 2
    if sigint is not None and sigint.received:
        # A SIGINT before rclpy.init found no context to shut down: the stop asked for.
        _try_shutdown_quietly()
        return 0
    node: Node | None = None
    lost: SharedMemoryPortLostError | None = None
    signalled = False
    try:
        try:
            if sigint is not None:
                sigint.starting = True
            node = factory()
        except ParameterValidationError as error:
            print(f"{program}: {error}", file=sys.stderr)
            return 2
        except Endo3dError as error:
            return report_error(program, error)
        finally:
            if sigint is not None:
                sigint.starting = False
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        node.create_timer(SHM_PORT_CHECK_PERIOD_S,
                          _lost_port_check(node, restart=restart_on_lost_port))
        # Logged once the executor exists: a process that sees this line is up.
        log_dds_environment(node)
        executor.spin()
    except SharedMemoryPortLostError as error:
        lost = error  # raised again below, unless a signal stopped the node meanwhile
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        # SIGINT may shut the context down while spin() builds its next wait
        # set (an RCLError, "failed to initialize wait set: the given context
        # is not valid") or while the factory still creates the node (rclpy's
        # NotInitializedException): that is the shutdown asked for, not a
        # failure (exit 1 and a traceback after SIGINT, seen in CI). With the
        # context still valid it is one, and propagates.
        if rclpy.ok():
            raise
    finally:
        if node is not None:
            close = getattr(node, "close", None)
            if callable(close):
                close()
            node.destroy_node()
        # SIGINT or SIGTERM (rclpy's handler) while closing shut the context down:
        # the stop asked for wins over a restart
        signalled = not rclpy.ok()
        # try_shutdown: SIGINT or the node itself may have shut the context
        # down already, and a later rclpy.init() in this process must work.
        rclpy.try_shutdown()
    if lost is not None and not signalled:
        raise lost
    return int(getattr(node, "exit_code", 0) or 0)


def _lost_port_check(node: Node, *, restart: bool) -> Callable[[], None]:
    """A timer callback: check the node's shared-memory ports (:mod:`endo_io.shm_ports`).

    With ``restart`` a lost port raises :class:`SharedMemoryPortLostError`
    out of ``spin()`` (:func:`run_node` creates the node again); without, it
    is logged as an error once.
    """
    watch = SharedMemoryPortWatch()
    logged = False

    def check() -> None:
        nonlocal logged
        try:
            watch.check()
        except SharedMemoryPortLostError as error:
            if restart:
                raise
            if not logged:
                node.get_logger().error(f"{error}; restart this node to be reachable again")
                logged = True

    return check


def _program(argv: Sequence[str]) -> str:
    """The program's name in messages: its command's file name."""
    return Path(argv[0]).name if argv else "node"


def _refused_arguments(error: Exception) -> str:
    """One line from rcl's refusal of a node's ROS arguments (its source positions cut)."""
    reason = re.split(r", at /", str(error).splitlines()[0])[0]
    return f"cannot start with these ROS arguments: {reason}"


def check_ros_arguments(argv: Sequence[str]) -> None:
    """Parse a node's command line as its start will (``rclpy.init``), starting nothing.

    rcl reads the ``--ros-args`` block: a ``--params-file`` that does not
    parse or is not a ROS parameter file, a malformed ``-p`` value or remap.
    The parse runs in a context of its own that is shut down at once (no
    node, no DDS participant); rcl's own ``[ERROR]`` line is kept off stderr.

    Args:
        argv: the node's command line, program first.

    Raises:
        RosArgumentsError: rcl refuses them; the one line ``run_node``
            would print.
    """
    from rclpy.context import Context

    context = Context()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as quiet:  # noqa: PTH123
            os.dup2(quiet.fileno(), 2)
            try:
                rclpy.init(args=list(argv), context=context)
            finally:
                os.dup2(saved, 2)
    except _rclpy.RCLError as error:
        raise RosArgumentsError(_refused_arguments(error)) from None
    finally:
        os.close(saved)
    rclpy.try_shutdown(context=context)


def split_ros_args(argv: Sequence[str]) -> tuple[list[str], list[str]]:
    """Split a command line into (our arguments, ROS arguments).

    ROS arguments are the ``--ros-args ... [--]`` blocks; they go to
    ``rclpy.init`` (with the program name first), everything else to argparse.
    Unlike ``rclpy.utilities.remove_ros_args``, a ``FROM:=TO`` value of our own
    ``--remap`` option stays ours: rcl would otherwise take it for a
    (deprecated) bare remap rule.
    """
    ours: list[str] = []
    ros: list[str] = list(argv[:1])
    inside = False
    for arg in argv[1:]:
        if arg == "--ros-args":
            inside = True
            ros.append(arg)
        elif inside and arg == "--":
            inside = False
            ros.append(arg)
        elif inside:
            ros.append(arg)
        else:
            ours.append(arg)
    return ours, ros
