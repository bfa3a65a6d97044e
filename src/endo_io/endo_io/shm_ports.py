"""Whether this process still receives on its Fast DDS shared-memory ports.

Why: Fast DDS 2.x (the Jazzy wheels carry 2.14) names each participant's
receiving port ``/dev/shm/fastrtps_port<N>``; senders open it by that name
(3.x names them ``fastdds_port<N>``: there this watch finds nothing). Under
CPU starvation (a listener that does not answer the port's health check
within about a second: a loaded two-core CI host, a node warming up) the
watchdog marks the port bad, and an opener (``open_port_internal``) or a
sender's port going away (``~Port``) can remove the port's file by name and
create it anew while the listener still waits on the old, now nameless
segment (eProsima/Fast-DDS#5469, still open; reproduced here with the
endo3d profile: one SIGSTOP of 4 s in 16). From then on the senders that had the
old segment open still reach the node, and every other one, including any
publisher started later, writes into the new file, which nobody reads: the
node is matched on every topic and hears nothing, for good. CI saw a
restarted flow node receive its poses and none of its images for minutes.

The state shows in the process's own tables: it holds the port's lock file
(``fastrtps_port<N>_el``: the exclusive reader) but has no mapping of the
segment that now carries the port's name (``/proc/self/maps`` keeps the old
one, by inode, marked ``(deleted)``). :class:`SharedMemoryPortWatch` checks
this every :data:`CHECK_PERIOD_S`; a port is lost when every check has found
it so for :data:`CONFIRM_S` (a port that Fast DDS regenerates, or heals once
its listener runs again, is lost for an instant or a few seconds). Then
:func:`endo_io.process.run_node` logs one line and, for the processing
nodes (``restart_on_lost_port``), creates the node again in the process
with a new participant, after :func:`reserve_ports` has locked the lost
ports so that the new participant takes others: on the same port number
it was taken again, every few seconds, by the senders still trying the
old participant's locator (tested: ``test_shm_ports.py``).

Linux only: where ``/proc`` or ``/dev/shm`` do not exist the watch finds nothing.
"""

from __future__ import annotations

import fcntl
import os
import re
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

#: Where Fast DDS (through Boost.Interprocess) keeps its shared-memory files on Linux
#: (resolved: /proc shows the real path where /dev/shm is a link, e.g. to /run/shm).
SHM_DIR = Path("/dev/shm").resolve()

#: How often a node checks its ports, seconds.
CHECK_PERIOD_S = 2.0
#: How long a port must have been lost at every check to be lost, seconds.
CONFIRM_S = 5.0

_PORT_LOCK = re.compile(r"^fastrtps_port(\d+)_el$")
# /proc/<pid>/maps: address perms offset dev inode path [(deleted)]
_MAPS_LINE = re.compile(r"^\S+\s+\S+\s+\S+\s+\S+\s+(\d+)\s+(\S+)(?: \(deleted\))?$")


class SharedMemoryPortLostError(RuntimeError):
    """This process listens on a shared-memory port whose name now belongs to another segment.

    Not bad input (not an :class:`endo_io.errors.Endo3dError`): the
    transport itself lost the node's port, and only a new DDS participant
    gets it back.

    Attributes:
        ports: the lost port numbers.
    """

    def __init__(self, message: str, ports: tuple[int, ...]) -> None:
        super().__init__(message)
        self.ports = ports


@dataclass(frozen=True)
class LostPort:
    """A receiving port this process holds whose current segment it does not map.

    Attributes:
        port: the port number (``fastrtps_port<port>``), the participant's unicast port.
        mapped_inodes: inodes of the port's segments this process maps (the
            old one, nameless now).
        current_inode: inode of the file that carries the port's name now,
            or None when no file carries it.
    """

    port: int
    mapped_inodes: frozenset[int]
    current_inode: int | None

    def describe(self) -> str:
        """One line for the log: which port, and what its name points to now."""
        now = ("no file carries its name" if self.current_inode is None
               else f"its name belongs to another segment (inode {self.current_inode})")
        return (f"shared-memory port {self.port} was taken from this node: it receives on the "
                f"old segment, {now}, so publishers that open the port now cannot reach it "
                "(a Fast DDS race under CPU starvation, eProsima/Fast-DDS#5469)")


def held_ports(fd_targets: Iterable[str]) -> set[int]:
    """The ports whose exclusive-reader lock (``fastrtps_port<N>_el``) is among ``fd_targets``.

    Args:
        fd_targets: where this process's open file descriptors point
            (``readlink /proc/self/fd/*``).
    """
    ports = set()
    for target in map(Path, fd_targets):
        match = _PORT_LOCK.match(target.name)
        if match and target.parent == SHM_DIR:
            ports.add(int(match.group(1)))
    return ports


def mapped_port_inodes(maps_text: str) -> dict[int, set[int]]:
    """Inodes of the port segments (``fastrtps_port<N>``) mapped, by port.

    Args:
        maps_text: the process's ``/proc/<pid>/maps``.
    """
    found: dict[int, set[int]] = {}
    for line in maps_text.splitlines():
        if "fastrtps_port" not in line:  # most lines: a check runs on the executor's thread
            continue
        match = _MAPS_LINE.match(line.strip())
        if match is None:
            continue
        path = Path(match.group(2))
        port = re.fullmatch(r"fastrtps_port(\d+)", path.name)
        if port is not None and path.parent == SHM_DIR:
            found.setdefault(int(port.group(1)), set()).add(int(match.group(1)))
    return found


def lost_ports(held: Iterable[int], mapped: dict[int, set[int]],
               current_inode: Callable[[int], int | None]) -> list[LostPort]:
    """The held ports whose current segment (by name) is not among the ones mapped.

    Args:
        held: ports this process listens on (:func:`held_ports`).
        mapped: their mapped segments' inodes (:func:`mapped_port_inodes`).
        current_inode: the inode of the file named ``fastrtps_port<N>`` now,
            None when there is none.

    Returns:
        The lost ports, by port number. A held port that maps nothing is not
        listed (a port being opened, or not one this module understands).
    """
    lost = []
    for port in sorted(held):
        inodes = mapped.get(port)
        if not inodes:
            continue
        now = current_inode(port)
        if now not in inodes:
            lost.append(LostPort(port, frozenset(inodes), now))
    return lost


def _current_inode(port: int) -> int | None:
    try:
        return (SHM_DIR / f"fastrtps_port{port}").stat().st_ino
    except OSError:
        return None


def fd_targets(fd_dir: Path) -> list[str]:
    """Where the open file descriptors listed in ``fd_dir`` (``/proc/<pid>/fd``) point."""
    targets: list[str] = []
    try:
        entries = list(fd_dir.iterdir())
    except OSError:
        return targets
    for entry in entries:
        try:
            targets.append(str(entry.readlink()))
        except OSError:  # closed since the listing
            continue
    return targets


def this_process_lost_ports(proc: Path = Path("/proc/self")) -> list[LostPort]:
    """:func:`lost_ports` of this process (empty where ``/proc`` cannot be read)."""
    try:
        maps = (proc / "maps").read_text()
    except OSError:
        return []
    return lost_ports(held_ports(fd_targets(proc / "fd")), mapped_port_inodes(maps),
                      _current_inode)


class SharedMemoryPortWatch:
    """Raises when a receiving port has stayed lost for ``confirm_s`` at every check.

    A port that Fast DDS regenerates, or heals once its starved listener runs
    again, is lost for an instant or a few seconds (up to 2.7 s seen with a
    listener stopped for 4 s): a port is confirmed lost only when every check
    found it lost since one at least ``confirm_s`` earlier. Which segment its
    name points to may change meanwhile: a sender still trying the old
    participant's locator removes and recreates the file every second or so.

    Args:
        find: what to check (:func:`this_process_lost_ports`; a test passes its own).
        confirm_s: how long a port must stay lost, seconds.
        clock: monotonic seconds (a test passes its own).
    """

    def __init__(self, find: Callable[[], list[LostPort]] = this_process_lost_ports, *,
                 confirm_s: float = CONFIRM_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._find = find
        self._confirm_s = confirm_s
        self._clock = clock
        self._lost_since: dict[int, float] = {}  # port -> first of the checks that found it lost

    def check(self) -> None:
        """Check once (a timer's callback).

        Raises:
            SharedMemoryPortLostError: a port has been lost at every check for
                ``confirm_s`` or more; the error names it and carries every port
                lost now (a new participant should take none of them).
        """
        now = self._clock()
        lost = self._find()
        self._lost_since = {port.port: self._lost_since.get(port.port, now) for port in lost}
        confirmed = [port for port in lost if now - self._lost_since[port.port] >= self._confirm_s]
        if confirmed:
            raise SharedMemoryPortLostError("; ".join(port.describe() for port in confirmed),
                                            tuple(port.port for port in lost))


#: Lock files this process holds so that no participant of its takes those ports again.
_reserved: list[int] = []


def reserve_ports(ports: Iterable[int]) -> list[int]:
    """Hold the exclusive-reader lock of ``ports`` for the rest of this process's life.

    Called once the participant that lost them is gone, before a new one
    starts: Fast DDS gives a new participant the lowest free port, which
    would be a lost one again, and senders that still try the old
    participant's locator remove and recreate that port's file by name
    while they do (they hold segments with no listener), taking it from the
    new participant too. Locked here, the port is busy to Fast DDS, and the
    new participant takes the next one, which no sender has touched.

    Returns:
        The ports now held (a port whose lock another process holds is
        skipped: it is busy to Fast DDS already).
    """
    held = []
    for port in ports:
        if _reserve(SHM_DIR / f"fastrtps_port{port}_el"):
            held.append(port)
    return held


def _reserve(path: Path, attempts: int = 5) -> bool:
    """Lock ``path`` (created if missing) for this process's life; whether it is held."""
    for _ in range(attempts):
        try:
            descriptor = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError:
            return False
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
            # Fast DDS removes lock files by name (a sender's zombie probe does):
            # a lock on a file that lost its name reserves nothing, so try again
            same = os.fstat(descriptor).st_ino == path.stat().st_ino
        except OSError:
            same = False
        if same:
            _reserved.append(descriptor)
            return True
        os.close(descriptor)
        time.sleep(0.01)
    return False
