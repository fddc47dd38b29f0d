"""DDS domains reserved per process, so that runs on one machine never see each other.

Two processes that pick the same ROS_DOMAIN_ID exchange topics: a test run's simulated arm can
then be commanded by another run's controller. A domain is reserved by holding an exclusive
lock on a file named after it, for as long as the process lives; the demo, the benchmarks and
the tests all reserve their domains this way. (No rclpy import: usable before rclpy.init.)
"""
import atexit
import fcntl
import os
import tempfile

DOMAINS = 232  # Fast DDS: ports 7400 + 250 * domain must stay below 65536
_HELD = []     # lock files of the reserved domains, open until the process ends
atexit.register(lambda: [fh.close() for fh in _HELD])  # releases the locks (and no ResourceWarning)


def reserve_domains(count, start=None):
    """`count` DDS domains from 1..DOMAINS that no other process on this machine holds, searching
    from `start` (default: from the process id); each stays reserved while this process lives."""
    start = os.getpid() if start is None else start
    found = []
    for k in range(DOMAINS):
        domain = 1 + (start + k) % DOMAINS
        fh = open(os.path.join(tempfile.gettempdir(), f'lie_dynamics_dds_domain_{domain}.lock'), 'w')
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:  # another process holds it
            fh.close()
            continue
        _HELD.append(fh)
        found.append(domain)
        if len(found) == count:
            return found
    raise RuntimeError('no free DDS domain on this machine')
