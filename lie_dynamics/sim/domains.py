"""DDS domains reserved per process, so that runs on one machine never see each other.

Two processes that pick the same ROS_DOMAIN_ID exchange topics: a test run's simulated arm can
then be commanded by another run's controller. A domain is reserved by holding an exclusive
lock on a file named after it in /tmp (machine-wide, as the domains are), for as long as the
process lives; the demo, the benchmarks and the tests all reserve their domains this way. At exit
the files are removed (under the lock, so no other process can hold a lock on a removed file:
see `_lock`).
(No rclpy import: usable before rclpy.init.)
"""
import atexit
import fcntl
import os
import tempfile

DOMAINS = 232  # Fast DDS: ports 7400 + 250 * domain must stay below 65536
_HELD = []     # (path, fd) of the reserved domains, locked until release_domains or exit


# DDS domains are machine-wide, so their locks must be too: in the system's /tmp whatever
# TMPDIR says (two runs with their own TMPDIR once reserved the same domain and saw each other's
# topics); the process's temp dir only where /tmp cannot be written.
LOCK_DIR = '/tmp'
LOCK_DIR_ENV = 'LIE_DYNAMICS_DOMAIN_LOCK_DIR'   # another folder (tests isolate themselves with it)


def lock_dir():
    """Where the domains' lock files live: $LIE_DYNAMICS_DOMAIN_LOCK_DIR, else /tmp, else the
    temp dir."""
    folder = os.environ.get(LOCK_DIR_ENV)
    if folder:
        return folder
    return LOCK_DIR if os.access(LOCK_DIR, os.W_OK | os.X_OK) else tempfile.gettempdir()


def lock_path(domain):
    """The lock file of a domain."""
    return os.path.join(lock_dir(), f'lie_dynamics_dds_domain_{domain}.lock')


def _lock(path):
    """A descriptor holding the exclusive lock of `path`, or None if another process holds it.

    The holder removes the file while it still holds the lock. A process that opened the file
    before that and gets the lock afterwards holds it on a removed file, which reserves
    nothing: it sees that the path no longer names its file (stat vs fstat) and starts again."""
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:  # another process holds it
            os.close(fd)
            return None
        try:
            st = os.stat(path)
        except FileNotFoundError:
            st = None
        mine = os.fstat(fd)
        if st is not None and (st.st_dev, st.st_ino) == (mine.st_dev, mine.st_ino):
            return fd
        os.close(fd)


def reserve_domains(count, start=None):
    """`count` DDS domains from 1..DOMAINS that no other process on this machine holds, searching
    from `start` (default: from the process id); each stays reserved until the process exits
    (or release_domains)."""
    start = os.getpid() if start is None else start
    found = []
    for k in range(DOMAINS):
        domain = 1 + (start + k) % DOMAINS
        path = lock_path(domain)
        fd = _lock(path)
        if fd is None:
            continue
        _HELD.append((path, fd))
        found.append(domain)
        if len(found) == count:
            return found
    raise RuntimeError('no free DDS domain on this machine')


def release_domains():
    """Give back every domain this process reserved and remove its lock files (also at exit)."""
    while _HELD:
        path, fd = _HELD.pop()
        try:
            os.unlink(path)  # still locked: nobody can be holding this file
        except FileNotFoundError:
            pass
        os.close(fd)


atexit.register(release_domains)
