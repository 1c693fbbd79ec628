"""ROS domain ids for graph runs: valid, free, and held for the whole run.

Every ``rotortwin compare`` / ``regress`` runs its nodes on one ``ROS_DOMAIN_ID`` with
localhost-only discovery.  Two runs on one domain would see each other's topics, so a
run *leases* its domain:

- a lease is an exclusive ``flock`` on ``<lock dir>/domain-<id>.lock`` (lock dir:
  ``$ROTORTWIN_LOCK_DIR``, else ``<tmp>/rotortwin-domains``), held until the run ends.
  The kernel drops it when the process dies, even by ``kill -9``, so a lock never
  outlives its run;
- without ``--domain-id`` the first free id of 1..101 (in random order) is taken: not
  leased by another run and with no DDS participant on it (Fast DDS binds UDP
  ``7410 + 250·id`` for a domain's first participant; a port in use means someone is
  there, e.g. a ``ros2`` daemon);
- an explicit id must be 0..232 (Fast DDS's port mapping ``7400 + 250·id`` runs out of
  UDP ports above 232; 0..101 also stays clear of Linux's ephemeral ports) and not
  leased by another run; other participants are allowed (a ``rotortwin monitor``
  started first on the same id is how one watches a run).
"""

from __future__ import annotations

import errno
import os
import random
import socket
import tempfile
from pathlib import Path

from twin_nodes.base.errors import TwinError

__all__ = ["DOMAIN_MAX", "AUTO_DOMAINS", "check_domain_id", "participant_port_busy", "DomainLease",
           "lease_domain", "lock_dir"]

#: highest domain id Fast DDS can map to UDP ports (7400 + 250·id + offsets <= 65535)
DOMAIN_MAX = 232
#: ids picked automatically: clear of Linux's ephemeral port range (32768+)
AUTO_DOMAINS = range(1, 102)


def check_domain_id(domain_id: object, option: str = "--domain-id") -> int:
    """``domain_id`` as an int in 0..232, else a one-line :class:`TwinError`."""
    try:
        d = int(domain_id)  # type: ignore[call-overload]
        ok = not isinstance(domain_id, bool) and float(domain_id) == d and 0 <= d <= DOMAIN_MAX  # type: ignore[arg-type]
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        raise TwinError(f"{option}: expected a ROS domain id 0..{DOMAIN_MAX} (Fast DDS maps id to UDP ports "
                        f"7400 + 250*id; 0..101 also avoids Linux's ephemeral ports), got {domain_id!r}")
    return d


def participant_port_busy(domain_id: int) -> bool:
    """True if the UDP port of a first DDS participant on ``domain_id`` is in use."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.bind(("0.0.0.0", 7400 + 250 * int(domain_id) + 10))
    except OSError as exc:
        return exc.errno == errno.EADDRINUSE
    finally:
        s.close()
    return False


def lock_dir() -> Path:
    d = Path(os.environ.get("ROTORTWIN_LOCK_DIR") or Path(tempfile.gettempdir()) / "rotortwin-domains")
    try:
        d.mkdir(parents=True, exist_ok=True)
        if d.stat().st_uid == os.getuid():
            os.chmod(d, 0o1777)  # shared by every user's runs (sticky: each removes only its own files)
    except OSError:
        pass
    return d


class DomainLease:
    """An exclusive lock on one domain id for the life of a run (``release()`` or process exit)."""

    def __init__(self, domain_id: int, fd: int | None, path: Path | None):
        self.domain_id = domain_id
        self._fd = fd
        self.path = path

    def release(self) -> None:
        if self._fd is not None:
            try:
                os.close(self._fd)  # drops the flock
            except OSError:
                pass
            self._fd = None

    def __enter__(self) -> "DomainLease":
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def _try_lock(domain_id: int) -> tuple[bool, DomainLease | None, str]:
    """(got it, lease, holder): ``holder`` names the run that holds it when taken."""
    import fcntl

    path = lock_dir() / f"domain-{domain_id}.lock"
    fd = None
    for flags in (os.O_RDWR | os.O_CREAT, os.O_RDONLY):
        try:
            fd = os.open(path, flags, 0o666)
            break
        except OSError:
            continue
    if fd is None:
        return True, DomainLease(domain_id, None, None), ""  # cannot lock here: nothing to coordinate with
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        try:
            holder = os.pread(fd, 64, 0).decode("ascii", "replace").strip()
        except OSError:
            holder = ""
        os.close(fd)
        return False, None, holder
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        if os.fstat(fd).st_uid == os.getuid():
            os.fchmod(fd, 0o666)
    except OSError:
        pass
    return True, DomainLease(domain_id, fd, path), ""


def lease_domain(domain_id: int | None = None, candidates: list[int] | None = None) -> DomainLease:
    """Lease ``domain_id`` (refused in one line if another run holds it), or the first free one."""
    if domain_id is not None:
        d = check_domain_id(domain_id)
        ok, lease, holder = _try_lock(d)
        if not ok or lease is None:
            who = f" (pid {holder})" if holder else ""
            raise TwinError(f"--domain-id: ROS domain {d} is in use by another rotortwin run{who}; "
                            "pick another id, or leave --domain-id out to get a free one")
        return lease
    ids = list(candidates) if candidates is not None else list(AUTO_DOMAINS)
    if candidates is None:
        random.shuffle(ids)
    for d in ids:
        if participant_port_busy(d):
            continue
        ok, lease, _ = _try_lock(d)
        if ok and lease is not None:
            return lease
    raise TwinError(f"no free ROS domain id among {len(ids)} candidates (all leased by rotortwin runs or with "
                    "DDS participants); pass --domain-id")
