"""DDS-domain reservation (lie_dynamics.sim.domains): exclusive across processes, and nothing left
in the lock folder once the processes that reserved domains have ended. Each process here gets a
private lock folder (LIE_DYNAMICS_DOMAIN_LOCK_DIR) and TMPDIR, so the check sees only the files
these processes made."""
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESERVE = ('import os, sys, tempfile\n'
           'from lie_dynamics.sim import domains\n'
           'from lie_dynamics.sim.domains import reserve_domains\n'
           'print(*reserve_domains(int(sys.argv[1]), 0), flush=True)\n'
           'print(*sorted(os.listdir(domains.lock_dir())), flush=True)\n'
           'sys.stdin.read()  # hold them until told\n')


def _reserve(tmp, count, private_locks=True):
    env = {k: v for k, v in os.environ.items() if k != 'LIE_DYNAMICS_DOMAIN_LOCK_DIR'}
    env['TMPDIR'] = str(tmp)
    if private_locks:
        env['LIE_DYNAMICS_DOMAIN_LOCK_DIR'] = str(tmp)
    return subprocess.Popen([sys.executable, '-c', RESERVE, str(count)], cwd=ROOT, env=env,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)


def test_domains_are_exclusive_and_their_lock_files_go_with_the_process(tmp_path):
    tmp = tmp_path / 'tmp'
    tmp.mkdir()
    (tmp / 'lie_dynamics_dds_domain_4.lock').write_text('')  # what a killed process leaves behind
    holder = _reserve(tmp, 3)
    assert holder.stdout.readline().split() == ['1', '2', '3']
    held = holder.stdout.readline().split()
    assert held == [f'lie_dynamics_dds_domain_{d}.lock' for d in (1, 2, 3, 4)]
    other = _reserve(tmp, 2)
    out, _ = other.communicate('', timeout=60)
    assert other.returncode == 0
    assert out.split('\n')[0].split() == ['4', '5']  # the held ones are skipped, the stale one is reused
    # the other process's files are gone (the stale one with them), the holder's are still there
    assert sorted(os.listdir(tmp)) == [f'lie_dynamics_dds_domain_{d}.lock' for d in (1, 2, 3)]
    holder.communicate('', timeout=60)
    assert holder.returncode == 0
    assert os.listdir(tmp) == []


def test_a_test_run_leaves_nothing_in_the_temp_dir(tmp_path):
    """conftest.py's log/home folder and domain lock files go when the pytest process ends (its
    own tmp_path folders are under --basetemp here)."""
    tmp = tmp_path / 'tmp'
    tmp.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith(('PYTEST_', 'ROS_', 'LIE_DYNAMICS_'))}
    r = subprocess.run([sys.executable, '-m', 'pytest', '-q', '-p', 'no:cacheprovider', '-p', 'no:xdist',
                        '--basetemp', str(tmp_path / 'basetemp'),
                        'test/test_domains.py::test_domains_are_exclusive_and_their_lock_files_go_with_the_process'],
                       cwd=ROOT, env=dict(env, TMPDIR=str(tmp), LIE_DYNAMICS_DOMAIN_LOCK_DIR=str(tmp)),
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert os.listdir(tmp) == []


def test_runs_with_their_own_temp_dirs_never_share_a_domain(tmp_path):
    """DDS domains are machine-wide: two processes with different TMPDIRs (and no lock folder
    set) reserve from the same start and get disjoint domains, and neither leaves a file in its
    temp dir."""
    dirs = [tmp_path / 'a', tmp_path / 'b']
    for d in dirs:
        d.mkdir()
    first = _reserve(dirs[0], 3, private_locks=False)
    mine = set(first.stdout.readline().split())
    second = _reserve(dirs[1], 3, private_locks=False)
    theirs = set(second.stdout.readline().split())
    for p in (first, second):
        p.communicate('', timeout=60)
        assert p.returncode == 0
    assert len(mine) == len(theirs) == 3 and not mine & theirs
    assert os.listdir(dirs[0]) == os.listdir(dirs[1]) == []
