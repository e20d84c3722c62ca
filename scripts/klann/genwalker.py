"""Generate scenes/klann.yaml (six-leg Klann walker, planar chassis) from the single-leg numbers.

Run from the repo root with the venv: python scripts/klann/genwalker.py
"""
import math
import sys
from pathlib import Path
import numpy as np, pinocchio as pin, yaml
HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import legmodel as LM  # noqa: E402
from redmax_ros.core.spatial import placement

OMEGA = -2*math.pi
r6 = lambda x: float(np.round(x, 6)) + 0.0
def pose_dict(M):
    R = M.rotation; beta = math.atan2(R[0, 2], R[0, 0])
    assert np.allclose(R, pin.rpy.rpyToMatrix(np.array([0, beta, 0])), atol=1e-12)  # rotations about y only
    return {'pos': [r6(v) for v in M.translation], 'rpy': [0, r6(beta), 0]}
def flow(d):
    return yaml.safe_dump(d, default_flow_style=True, width=10000, sort_keys=False).strip()

LEGS = [  # name, mirrored (aft-facing), crank, layer y [m], phase psi [rad] (single-leg crank angle at walker q = 0)
    ('f1', False, 'crank_fwd', 0.06, 0.0), ('f2', False, 'crank_fwd', 0.10, -2*math.pi/3), ('f3', False, 'crank_fwd', 0.14, -4*math.pi/3),
    ('a1', True, 'crank_aft', -0.06, -math.pi/3), ('a2', True, 'crank_aft', -0.10, -math.pi), ('a3', True, 'crank_aft', -0.14, -5*math.pi/3)]
CRANK_Y = {'crank_fwd': 0.10, 'crank_aft': -0.10}
CH_Z = 0.36  # initial crank axle height [m]
# joint friction geometry of every pin (BISP, paper §5.2): 8 mm pins, 12 mm bearing length; mu = 0.2 by
# default, changed for all joints and loop pins at once with --set friction.joint_mu=...
JF = {'mu': 0.2, 'radius': 0.004, 'length': 0.012, 'points': 8}
FOOT_R = 0.0125  # foot contact sphere radius [m] (half the bar width W)

bodies, joints, sites, loops = [], [], [], []
bodies.append({'name': 'chassis', 'shape': {'type': 'box', 'size': [0.5, 0.32, 0.04]}, 'mass': 3.0})
joints.append({'name': 'chassis', 'type': 'planar', 'parent': 'world', 'child': 'chassis',
               'placement': {'rpy': [r6(math.pi/2), 0, 0]}, 'body_placement': {'rpy': [r6(-math.pi/2), 0, 0]},
               'q0': [0.0, CH_Z, 0.0], 'v0': [0.0, 0.0, 0.0]})
crank_parts = {c: [] for c in CRANK_Y}
leg_entries = []
for name, mir, crank, y, psi in LEGS:
    d = LM.leg_dict(mir)
    q, v, m = LM.solve_phase(mir, psi, OMEGA)
    J = {j['name']: j for j in d['joints']}
    qv = {jn: (q[m.joint_index[jn].idx_q], v[m.joint_index[jn].idx_v]) for jn in J}
    P = lambda j: placement(j['placement']['pos'], j['placement']['rpy'])
    BP = lambda j: placement(j['body_placement']['pos'])
    # the leg's crank arm, as a part of the crank body (frame at the axle, chassis-aligned at q = 0)
    F0 = P(J['crank']); F0.translation = np.zeros(3)
    arm = F0 * placement(rpy=[0, psi, 0]) * BP(J['crank'])
    arm.translation += np.array([0, y - CRANK_Y[crank], 0])
    crank_parts[crank].append((arm, d['bodies'][0]['shape']['size']))
    pin_M = arm * P(J['crank_pin'])
    ents = {'bodies': [], 'joints': [], 'sites': [], 'loops': []}
    for b in d['bodies'][1:]:
        ents['bodies'].append(dict(b, name=f"{b['name']}_{name}"))
    def jent(jn, parent, M):
        j = J[jn]; qq, vv = qv[jn]
        return {'name': f'{jn}_{name}', 'type': 'revolute', 'axis': 'y', 'parent': parent, 'child': f"{j['child']}_{name}",
                'placement': pose_dict(M), 'body_placement': {'pos': j['body_placement']['pos']}, 'q0': r6(qq), 'v0': r6(vv),
                'friction': JF}
    ents['joints'].append(jent('crank_pin', crank, pin_M))
    ents['joints'].append(jent('knee', f'connector_{name}', P(J['knee'])))
    for jn in ('lower_pivot', 'upper_pivot'):
        M = P(J[jn]); M.translation = M.translation + np.array([0, y, -LM.ZO])
        ents['joints'].append(jent(jn, 'chassis', M))
    for s in d['sites']:
        ents['sites'].append({'name': f"{s['name']}_{name}", 'body': f"{s['body']}_{name}", 'pos': s['pos']})
    for lp in d['loops']:
        ents['loops'].append({'name': f"{lp['name']}_{name}", 'a': f"{lp['a']}_{name}", 'b': f"{lp['b']}_{name}", 'rows': ['x', 'z'],
                              'axis': 'y', 'friction': JF})
    foot = next(s for s in d['sites'] if s['name'] == 'foot')
    ents['contacts'] = [{'name': f'foot_{name}', 'body': f"{foot['body']}_{name}", 'type': 'sphere', 'pos': foot['pos'], 'radius': FOOT_R}]
    leg_entries.append((name, mir, crank, y, psi, ents))

crank_bodies = []
for c, parts in crank_parts.items():
    # explicit mass properties: three aluminium arms (as in klann_leg) + a 10 mm aluminium shaft across the layers
    ms, coms, Is = [], [], []
    for M, (lx, ty, wz) in parts:
        mass = 2700*lx*ty*wz; Ib = mass/12*np.diag([ty*ty+wz*wz, lx*lx+wz*wz, lx*lx+ty*ty])
        ms.append(mass); coms.append(M.translation.copy()); Is.append(M.rotation @ Ib @ M.rotation.T)
    r, L = 0.005, 0.10; ms_ = 2700*math.pi*r*r*L
    ms.append(ms_); coms.append(np.zeros(3)); Is.append(np.diag([ms_*(3*r*r+L*L)/12, ms_*r*r/2, ms_*(3*r*r+L*L)/12]))
    mt = sum(ms); com = sum(mi*ci for mi, ci in zip(ms, coms))/mt
    I = sum(Ii + mi*((ci-com)@(ci-com)*np.eye(3) - np.outer(ci-com, ci-com)) for mi, ci, Ii in zip(ms, coms, Is))
    crank_bodies.append({'name': c, 'mass': float(round(mt, 6)), 'com': [r6(v) for v in com],
                         'inertia': [0.0 if abs(v) < 1e-15 else float('%.6g' % v) for v in (I[0,0], I[1,1], I[2,2], I[0,1], I[0,2], I[1,2])]})
    joints.append({'name': c, 'type': 'revolute', 'axis': 'y', 'parent': 'chassis', 'child': c,
                   'placement': {'pos': [0.0, CRANK_Y[c], 0.0]}, 'q0': 0.0, 'v0': r6(OMEGA), 'friction': JF})

out = []
w = out.append
w(open(HERE / 'walker_header.yaml').read().rstrip())
w('bodies:')
for b in bodies + crank_bodies: w('  - ' + flow(b))
for name, mir, crank, y, psi, e in leg_entries:
    w(f"  # leg {name}: {'aft' if mir else 'forward'}-facing, y = {y} m, on {crank}, phase {round(math.degrees(psi))} deg")
    for b in e['bodies']: w('  - ' + flow(b))
w('joints:')
for j in joints: w('  - ' + flow(j))
for name, mir, crank, y, psi, e in leg_entries:
    w(f"  # leg {name} (q0, v0: this leg's pose and loop-consistent speeds at crank phase {round(math.degrees(psi))} deg)")
    for j in e['joints']: w('  - ' + flow(j))
w('sites:')
for name, mir, crank, y, psi, e in leg_entries:
    for s in e['sites']: w('  - ' + flow(s))
w('loops:')
for name, mir, crank, y, psi, e in leg_entries:
    for lp in e['loops']: w('  - ' + flow(lp))
w('ground:')
w('  - ' + flow({'name': 'floor', 'normal': [0, 0, 1], 'offset': 0.0, 'mu': 0.8}))
w('contacts:')
for name, mir, crank, y, psi, e in leg_entries:
    for c in e['contacts']: w('  - ' + flow(c))
w('friction: ' + flow({'max_iter': 50, 'tol': 1e-5}))
w(open(HERE / 'walker_footer.yaml').read().rstrip())
open(HERE.parents[1] / 'scenes' / 'klann.yaml', 'w').write('\n'.join(out) + '\n')
