"""Single Klann leg numbers (front-facing or mirrored) as a scene dict, same conventions as scenes/klann_leg.yaml."""
import numpy as np
S, ZO, W, T = 0.0125, 0.345, 0.025, 0.006
SRC = {'O':(41.395,-26.641),'A':(27.690,-19.705),'B':(27.690,-31.092),'M':(36.033,-25.415),
       'N':(21.501,-22.089),'K':(10.879,-21.918),'L':(19.432,-32.923),'S':(0,0)}
BODIES = {'crank_arm':('O','M'), 'connector':('M','K'), 'leg':('L','S'), 'lower_rocker':('A','N'), 'upper_rocker':('B','L')}
JOINTS = [('crank','world','crank_arm','O'),('crank_pin','crank_arm','connector','M'),('knee','connector','leg','K'),
          ('lower_pivot','world','lower_rocker','A'),('upper_pivot','world','upper_rocker','B')]
SITES = [('lower_rocker_tip','lower_rocker','N'),('connector_lower','connector','N'),('upper_rocker_tip','upper_rocker','L'),
         ('leg_upper','leg','L'),('foot','leg','S')]
r6 = lambda x: float(np.round(x, 6)) + 0.0

def points(mirror=False):
    # world (x, z), crank axle at (0, ZO); front-facing: foot at +x; mirrored: foot at -x
    sx = 1.0 if mirror else -1.0
    return {k: np.array([sx*(x-SRC['O'][0])*S, (-y+SRC['O'][1])*S + ZO]) for k,(x,y) in SRC.items()}

def leg_dict(mirror=False):
    P = points(mirror)
    def frame(b):
        a,c = BODIES[b]; d = P[c]-P[a]; return (P[a]+P[c])/2, np.arctan2(d[1],d[0]), np.linalg.norm(d)
    def inv(b, p):
        c,phi,_ = frame(b); v = p-c; cp,sp = np.cos(phi),np.sin(phi)
        return [r6(cp*v[0]+sp*v[1]), 0.0, r6(-sp*v[0]+cp*v[1])]
    bodies = [{'name': b, 'shape': {'type':'box','size':[float(round(frame(b)[2]+W,4)), T, W]}, 'density': 2700} for b in BODIES]
    joints = []
    for n,p,c,j in JOINTS:
        _,phic,_ = frame(c)
        if p == 'world': pos = [r6(P[j][0]),0.0,r6(P[j][1])]; phip = 0.0
        else: pos = inv(p,P[j]); phip = frame(p)[1]
        bp = [-v+0.0 for v in inv(c,P[j])]
        joints.append({'name':n,'type':'revolute','axis':'y','parent':p,'child':c,
                       'placement':{'pos':pos,'rpy':[0,r6(-(phic-phip)),0]},'body_placement':{'pos':bp},'q0':0.0})
    sites = [{'name':s,'body':b,'pos':inv(b,P[p])} for s,b,p in SITES]
    loops = [{'name':'lower_rocker_connector','a':'lower_rocker_tip','b':'connector_lower','rows':['x','z']},
             {'name':'upper_rocker_leg','a':'upper_rocker_tip','b':'leg_upper','rows':['x','z']}]
    return {'name':'leg','gravity':[0,0,-9.81],'dt':1e-3,'bodies':bodies,'joints':joints,'sites':sites,'loops':loops}

def solve_phase(mirror, psi, omega):
    """Joint angles (crank = psi) on the assembled branch reached continuously from the published pose,
    and loop-consistent joint velocities for crank speed omega."""
    from redmax_ros.core.scene.loader import scene_from_dict
    from redmax_ros.core.model.mechanism import compile_scene
    from redmax_ros.core.dynamics.stabilization import project, loop_residual
    m = compile_scene(scene_from_dict(leg_dict(mirror)))
    d = m.model.createData(); q = m.q0.copy(); ci = m.joint_index['crank'].idx_q
    n = max(1, int(np.ceil(abs(psi - q[ci]) / 0.01)))
    for t in np.linspace(q[ci], psi, n + 1)[1:]:
        # predictor: first-order along the null space, then Newton with the crank held
        q[ci] = t
        q, err = project(m, d, q, hold_dofs=[ci], tol=1e-13, max_iter=50)
    assert err < 1e-12, err
    phi, G = loop_residual(m, d, q)
    A = np.vstack([G, np.eye(5)[ci]]); v = np.linalg.solve(A, np.r_[np.zeros(4), omega])
    return q, v, m

if __name__ == '__main__':
    import yaml
    for mir in (False, True):
        q, v, m = solve_phase(mir, 0.0, -2*np.pi); print(mir, q, v)
