"""Why replies wait during loads: the Linux scheduler's own record of bench.node_loads. While
node_loads runs, the kernel's sched_switch and sched_wakeup events are recorded (tracefs); then,
per process (the node, the streaming process, the build and trajectory processes, the
benchmark), every wait of one of its threads from being made runnable (woken, or preempted while
runnable) to running on a CPU: how many, percentiles, the largest, how many over 1 ms and, of
those, how many had another CPU idle for at least half of the wait (the waiting thread could have
run at once: the kernel kept it behind the task on its own CPU). The longest waits are listed
with what held the CPU and how long the other CPUs idled.

    python -m bench.probes.sched_trace [--raised] [--repeat R] [--quick] [--node-src DIR] [--out DIR]

Needs root and tracefs (/sys/kernel/tracing; mounted here if it is not). Prints the kernel's tick
rate and preemption model where /proc/config.gz says them, node_loads' table, then the waits;
saves a chart of the node's and the streaming process's waits (sched_trace.png in --out). The
tracing settings are put back afterwards, and tracefs unmounted if it was mounted here. A
benchmark, not a test: numbers depend on the machine.
"""
import argparse
import bisect
import gzip
import os
import re
import subprocess
import sys
import threading
import time
from collections import defaultdict

import numpy as np

from bench.common import HERE, savefig, setup_matplotlib

TRACEFS = '/sys/kernel/tracing'
EVENTS = ('sched/sched_switch', 'sched/sched_wakeup')
BUFFER_KB = 200_000   # per CPU: a whole node_loads run at 500 Hz holds about 1.5 M events
LONG_S = 1e-3         # a wait this long or longer is a long one
ROLES = (('lie_dynamics.dynamics_node', 'node'), ('bench.probes.node_trace', 'node'), ('--stream', 'streaming process'),
         ('build_process', 'build process'), ('trajectory_process', 'trajectory process'),
         ('--send-trajectory', 'trajectory sender'))

_LINE = re.compile(r'^\s*(.+?)-(\d+)\s+\(\s*([\d-]+)\)\s+\[(\d+)\]\s+\S+\s+([\d.]+): '
                   r'(sched_switch|sched_wakeup): (.*)$')
_SWITCH = re.compile(r'prev_comm=.* prev_pid=(\d+) prev_prio=\d+ prev_state=(\S+) ==> next_comm=(.*) next_pid=(\d+)')
_WAKEUP = re.compile(r'pid=(\d+) prio=\d+ target_cpu=(\d+)')


def parse(lines):
    """Scheduler events of a tracefs text trace recorded with record-tgid: (t, cpu, kind, fields,
    tid, tgid) with fields (prev tid, prev state, next comm, next tid) for a switch and (tid, the
    CPU it is queued on) for a wakeup; tgid None where the trace does not know it."""
    for line in lines:
        m = _LINE.match(line)
        if not m:
            continue
        kind, rest = m.group(6), m.group(7)
        f = (_SWITCH if kind == 'sched_switch' else _WAKEUP).search(rest)
        if f is None:
            continue
        tgid = int(m.group(3)) if m.group(3).isdigit() else None
        yield float(m.group(5)), int(m.group(4)), kind, f.groups(), int(m.group(2)), tgid


def waits(events):
    """(waits, tgid_of, busy): waits {tid: [(seconds, start, CPU queued on, CPU it ran on)]}, each
    from runnable (a wakeup, or a switch away while runnable) to running; tgid_of {tid: tgid};
    busy {cpu: [(start, end, comm, tid)]}, who ran on each CPU (tid 0: idle)."""
    ready, out, tgid_of, running, on_cpu = {}, defaultdict(list), {}, {}, set()
    busy = defaultdict(list)
    for t, cpu, kind, f, tid, tgid in events:
        if tgid is not None:
            tgid_of[tid] = tgid
        if kind == 'sched_wakeup':
            tid = int(f[0])
            if tid not in on_cpu:   # (a thread woken before it was switched out never waited)
                ready.setdefault(tid, (t, int(f[1])))
            continue
        prev, state, comm, nxt = int(f[0]), f[1], f[2], int(f[3])
        if cpu in running:
            busy[cpu].append((running[cpu][0], t) + running[cpu][1:])
        running[cpu] = (t, comm, nxt)
        on_cpu.discard(prev)
        on_cpu.add(nxt)
        ready.pop(prev, None)
        if prev and state.startswith('R'):   # preempted: runnable from now on
            ready[prev] = (t, cpu)
        if nxt in ready:
            start, queued = ready.pop(nxt)
            out[nxt].append((t - start, start, queued, cpu))
    return out, tgid_of, busy


def _overlap(segments, starts, a, b):
    """The parts of `segments` (sorted (start, end, ...)) inside [a, b]."""
    i = max(bisect.bisect_right(starts, a) - 1, 0)
    while i < len(segments) and segments[i][0] < b:
        s, e = segments[i][0], segments[i][1]
        if e > a:
            yield (max(s, a), min(e, b)) + segments[i][2:]
        i += 1


def attribute(wait, busy, starts):
    """For one wait (seconds, start, queued on, ran on): (idle seconds of the other CPUs than the
    one it was queued on, the longest, and who ran on that one meanwhile as [(seconds, comm, tid)],
    longest first)."""
    d, a, cpu, _ = wait
    b = a + d
    idle = 0.0
    for c in busy:
        if c != cpu:
            idle = max(idle, sum(e - s for s, e, _, tid in _overlap(busy[c], starts[c], a, b) if tid == 0))
    held = defaultdict(float)
    for s, e, comm, tid in _overlap(busy.get(cpu, []), starts.get(cpu, []), a, b):
        held[(comm, tid)] += e - s
    return idle, sorted(((v, k[0], k[1]) for k, v in held.items()), reverse=True)


def summary(out, tgid_of, busy, roles, long_s=LONG_S):
    """Per process of `roles` {tgid: name}: a row of its threads' waits, and the long waits with
    their attribution ([(seconds, role, cpu, idle, [(seconds, 'comm/tid (role)')])], longest first)."""
    starts = {c: [s[0] for s in busy[c]] for c in busy}
    rows, long_waits = [], []
    for tgid, role in roles.items():
        ws = sorted(w for tid, lst in out.items() if tgid_of.get(tid) == tgid for w in lst)
        if not ws:
            continue
        d = [w[0] for w in ws]
        longs = [w for w in ws if w[0] >= long_s]
        with_idle = 0
        for w in longs:
            idle, held = attribute(w, busy, starts)
            with_idle += idle >= 0.5 * w[0]
            held = [(s, f'{comm}/{tid}' + (f' ({roles[tgid_of[tid]]})' if tgid_of.get(tid) in roles else ''))
                    for s, comm, tid in held]
            long_waits.append((w[0], role, w[2], idle, held))
        p50, p99, p999 = np.percentile(d, (50, 99, 99.9))
        rows.append({'process': role, 'waits': len(d), 'p50_ms': 1e3 * p50, 'p99_ms': 1e3 * p99,
                     'p999_ms': 1e3 * p999, 'max_ms': 1e3 * d[-1], 'long': len(longs),
                     'long_other_cpu_idle': with_idle, 'all': d})
    long_waits.sort(key=lambda x: -x[0])
    return rows, long_waits


def kernel_facts():
    """The tick rate and preemption model of the running kernel, as its config says ('' unknown)."""
    try:
        with gzip.open('/proc/config.gz', 'rt') as fh:
            cfg = dict(ln.strip().split('=', 1) for ln in fh if ln.startswith('CONFIG_') and '=' in ln)
    except OSError:
        return ''
    model = next((k[len('CONFIG_PREEMPT_'):].lower() for k in ('CONFIG_PREEMPT_NONE', 'CONFIG_PREEMPT_VOLUNTARY',
                                                              'CONFIG_PREEMPT_LAZY', 'CONFIG_PREEMPT_RT')
                  if cfg.get(k) == 'y'), 'full' if cfg.get('CONFIG_PREEMPT') == 'y' else '?')
    return (f"kernel {os.uname().release}: CONFIG_HZ={cfg.get('CONFIG_HZ', '?')} (a tick every "
            f"{1000 / int(cfg.get('CONFIG_HZ', '1000')):.0f} ms), default preemption: {model}"
            f"{' (dynamic)' if cfg.get('CONFIG_PREEMPT_DYNAMIC') == 'y' else ''}")


class Recorder:
    """tracefs recording of EVENTS with tgids (tracefs mounted if it is not); `stop` returns the
    text trace's path; `restore` puts every setting back (and unmounts what it mounted)."""

    def __init__(self, root=TRACEFS):
        self.root = root
        self.mounted = False   # mounted here: unmounted by restore
        if not os.path.exists(os.path.join(root, 'trace')):
            self.mounted = subprocess.run(['mount', '-t', 'tracefs', 'nodev', root], check=False,
                                          capture_output=True).returncode == 0
        if not os.path.exists(os.path.join(root, 'trace')):
            raise RuntimeError(f'no tracefs at {root} (root: mount -t tracefs nodev {root})')
        self._saved = {p: self._read(p) for p in ('tracing_on', 'buffer_size_kb', 'options/record-tgid')
                       + tuple(f'events/{e}/enable' for e in EVENTS)}

    def _read(self, p):
        with open(os.path.join(self.root, p)) as fh:
            return fh.read().split()[0]

    def _write(self, p, v):
        with open(os.path.join(self.root, p), 'w') as fh:
            fh.write(str(v))

    def start(self):
        self._write('tracing_on', 0)
        self._write('trace', '')
        self._write('buffer_size_kb', BUFFER_KB)
        self._write('options/record-tgid', 1)
        for e in EVENTS:
            self._write(f'events/{e}/enable', 1)
        self._write('tracing_on', 1)

    def stop(self, path):
        self._write('tracing_on', 0)
        with open(os.path.join(self.root, 'trace'), 'rb') as src, open(path, 'wb') as dst:
            while chunk := src.read(1 << 20):
                dst.write(chunk)
        return path

    def restore(self):
        self._write('tracing_on', 0)
        self._write('trace', '')
        for p, v in self._saved.items():
            self._write(p, v)
        if self.mounted:
            subprocess.run(['umount', self.root], check=False, capture_output=True)


def watch_processes(stop, found, period=0.2):
    """(a thread) Until `stop`: every process whose command line names a role, by pid."""
    while not stop.is_set():
        for pid in filter(str.isdigit, os.listdir('/proc')):
            if int(pid) in found:
                continue
            try:
                with open(f'/proc/{pid}/cmdline', 'rb') as fh:
                    cmd = fh.read().replace(b'\0', b' ').decode(errors='replace')
            except OSError:
                continue
            role = next((name for key, name in ROLES if key in cmd), None)
            if role is not None:
                found[int(pid)] = role
        stop.wait(period)


def markdown(rows, long_waits, facts, n=8):
    out = [facts, '', '| process | waits | p50 ms | p99 ms | p99.9 ms | max ms | waits ≥ 1 ms '
           '| of those, another CPU idle ≥ half the wait |', '|---|---|---|---|---|---|---|---|']
    for r in rows:
        out.append(f"| {r['process']} | {r['waits']} | {r['p50_ms']:.3f} | {r['p99_ms']:.3f} | {r['p999_ms']:.3f} | "
                   f"{r['max_ms']:.2f} | {r['long']} | {r['long_other_cpu_idle']} |")
    out += ['', f'The {n} longest waits:', '']
    for d, role, cpu, idle, held in long_waits[:n]:
        who = ', '.join(f'{name} {1e3 * s:.2f} ms' for s, name in held[:3]) or '?'
        out.append(f'- {1e3 * d:.2f} ms, {role}, queued on CPU {cpu} held by {who}; another CPU idle '
                   f'{1e3 * idle:.2f} ms')
    return '\n'.join(out)


def chart(rows, path):
    plt = setup_matplotlib()
    fig, ax = plt.subplots(figsize=(7, 4))
    for r in rows:
        if r['process'] in ('node', 'streaming process'):
            d = [1e3 * x for x in r['all']]
            ax.plot(d, [1 - i / len(d) for i in range(len(d))], label=r['process'])
    ax.set_xscale('log')
    ax.set_yscale('log')
    ax.set_xlabel('wait from runnable to running (ms)')
    ax.set_ylabel('share of waits at least this long')
    ax.set_title('bench.probes.sched_trace: waits for a CPU during bench.node_loads')
    ax.legend()
    fig.tight_layout()
    savefig(fig, path)


def main(argv=None):
    ap = argparse.ArgumentParser(prog='python -m bench.probes.sched_trace', description=__doc__.split('\n')[0])
    ap.add_argument('--raised', action='store_true', help='caps raised (node_loads --raised)')
    ap.add_argument('--repeat', type=int, default=1, help='runs of each event (node_loads --repeat)')
    ap.add_argument('--quick', action='store_true', help='no trajectory event')
    ap.add_argument('--node-src', help='run the node of this checkout instead')
    ap.add_argument('--out', default=os.path.join(HERE, 'out'))
    a = ap.parse_args(argv)
    from bench import node_loads
    try:
        rec = Recorder()
    except (RuntimeError, OSError) as exc:
        print(f'bench.probes.sched_trace: {exc}', file=sys.stderr)
        return 2
    os.makedirs(a.out, exist_ok=True)
    found, stop = {}, threading.Event()
    watcher = threading.Thread(target=watch_processes, args=(stop, found), daemon=True)
    path = os.path.join(a.out, 'sched_trace.txt')
    try:
        watcher.start()
        rec.start()
        t0 = time.monotonic()
        result = node_loads.run(a.raised, 0, a.quick, a.repeat, a.node_src)
        rec.stop(path)
    finally:
        stop.set()
        rec.restore()
    try:
        print(node_loads.markdown(result, a.raised, 0), '\n')
        found[os.getpid()] = 'benchmark'
        with open(path, encoding='utf-8', errors='replace') as fh:
            rows, long_waits = summary(*waits(parse(fh)), found)
    finally:
        os.remove(path)   # hundreds of MB of text
    print(markdown(rows, long_waits, kernel_facts()))
    print(f'\n({time.monotonic() - t0:.0f} s recorded)')
    chart(rows, os.path.join(a.out, 'sched_trace.png'))
    return 0


if __name__ == '__main__':
    sys.exit(main())
