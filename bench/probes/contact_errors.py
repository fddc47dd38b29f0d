"""Where the contact bench's errors come from, push by push (docs/benchmarks.md, section 11).

    python -m bench.probes.contact_errors [--pushes 40] [--seed 2]

The pushes of bench.contact (same plant, hold, thresholds and noise), with the simulator's
J^T F beside the node's estimate at every sample of the push. Per robot and noise level:
  * the residual's error against J^T F at the push's end (per sample, and the node's mean
    `ContactIsolation.residual` against J^T F of the last 0.1 s), in units of each joint's
    threshold: with exact efforts what is left is integration and model mismatch;
  * the pushed link's own joint torque (the smallest |J^T F| of its own joints / threshold): a
    push whose own joints feel little looks like a push on the link before;
  * links with 6 or more supporting joints: the force error against the effort noise propagated
    through the fit, |P_f sigma| / |F| (P the fit's pseudo-inverse, sigma the noise of a mean over
    0.3 s: NOISE x threshold x sqrt(dt / 0.3)): their ratio, and the misses of 5 % with the
    prediction beside them;
  * the hold's stability: the largest dt x eig(M^-1 K_d) over the pushes' states, with the damping
    of bench.contact.hold_gains and with the diagonal one it replaced (2 sqrt(kp M_jj)).
"""
import argparse

import numpy as np

import bench.contact as bc
from lie_dynamics.algorithms import contact_isolation as ci
from lie_dynamics.ros.features.contact_link import ContactIsolation


def push(model, settings, q0, link, wrench_mf, rng, noise):
    """One push through the node's parts: (q, r, J^T F per sample of the push, the node's mean at the end)."""
    iso = ContactIsolation()
    iso.adopt(settings, model)
    qs, rs, taus, mean = [], [], [], [None]

    def sample(t, sim, out, pubs):
        if t >= bc.START:
            qs.append(sim.q.copy())
            rs.append(out[0].copy())
            taus.append(sim.external_torque.copy())
            mean[0] = iso.residual.copy()
    bc.run_push(model, settings, q0, link, wrench_mf, rng, noise, {'default': iso}, bc.START + bc.PUSH_S, sample)
    return np.array(qs), np.array(rs), np.array(taus), mean[0]


def run(pushes, seed):
    rng = np.random.default_rng(seed)
    for name, model, _ in bc.robots():
        settings = bc.settings_for(model)
        th = np.asarray(settings.collision.threshold)
        tree = ci.tree(model)
        links = bc.pushable_links(model)
        stab = [0.0, 0.0]
        for noise in (0.0, bc.NOISE):
            err_inst, err_mean, own, ratio, misses = [], [], [], [], []
            for _ in range(pushes):
                drawn = bc.draw_push(model, links, th, rng)
                if drawn is None:
                    continue
                q0, link, p, f, _ = drawn
                M = model.mass_matrix(q0)
                kp, kd = bc.hold_gains(model, q0)
                stab[0] = max(stab[0], bc.DT * np.abs(np.linalg.eigvals(np.linalg.solve(M, kd))).max())
                diag = 2.0 * np.sqrt(kp * np.diag(M))
                stab[1] = max(stab[1], bc.DT * np.abs(np.linalg.eigvals(np.linalg.solve(M, np.diag(diag)))).max())
                qs, rs, taus, mean = push(model, settings, q0, link, np.concatenate([np.cross(p, f), f]), rng, noise)
                expected = bc.body_link(model, link)
                b = model.body_link_names.index(expected)
                err_inst.append(np.max(np.abs(rs[-1] - taus[-1]) / th))
                err_mean.append(np.max(np.abs(mean - taus[-100:].mean(axis=0)) / th))
                if tree.own[b].any():
                    own.append(np.min(np.abs(taus[-1][tree.own[b]]) / th[tree.own[b]]))
                if tree.support[b].sum() >= 6:
                    est = ci.link_wrench(model, qs[-1], mean, expected)
                    T = np.linalg.inv(model.link_pose(expected, qs[-1])) @ model.link_pose(link, qs[-1])
                    fe = np.linalg.norm(est.wrench[:3] - T[:3, :3] @ f) / np.linalg.norm(f)
                    pred = np.linalg.norm(est.inverse[:3] * (bc.NOISE * th * np.sqrt(bc.DT / 0.3))) / np.linalg.norm(f)
                    if noise > 0:
                        ratio.append(fe / pred)
                    if fe > 0.05:
                        misses.append(f'{100 * fe:.1f} % (predicted {100 * pred:.1f} %, rank {est.rank})')
            own = np.array(own)
            print(f'{name}, noise {noise} x threshold, {pushes} pushes:')
            print(f'  residual - J^T F at the end, x threshold: per sample median {np.median(err_inst):.2g} max '
                  f'{np.max(err_inst):.2g}; node mean median {np.median(err_mean):.2g} max {np.max(err_mean):.2g}')
            print('  pushed link\'s own joint torque / threshold: ' + ', '.join(
                f'< {x:g}: {int((own < x).sum())}' for x in (0.05, 0.02, 0.01, 0.003)) + f' of {own.size}')
            if ratio:
                print(f'  force error / noise prediction (>= 6 joints): median {np.median(ratio):.2f}')
            print('  force misses of 5 % (>= 6 joints): ' + ('; '.join(misses) or 'none'))
        print(f'  hold: max dt x eig(M^-1 K_d) {stab[0]:.2f} (diagonal damping from M\'s diagonal: {stab[1]:.2f}; '
              'explicit damping is unstable above 2)')


def main(argv=None):
    ap = argparse.ArgumentParser(prog='python -m bench.probes.contact_errors', description=__doc__.split('\n')[0])
    ap.add_argument('--pushes', type=int, default=40)
    ap.add_argument('--seed', type=int, default=2)
    args = ap.parse_args(argv)
    run(args.pushes, args.seed)


if __name__ == '__main__':
    main()
