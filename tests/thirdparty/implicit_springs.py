#!/usr/bin/env python3
"""implicit_springs: the distillation's time-stepping floor (the book, "Distilling a springtime surrogate").

Steps the spring surrogate of a distilled latent run (RUN/surrogate.json) by full-space implicit
Euler at the run's frame rate - the same incremental potential as the latent loss, without the
latent manifold: Newton with per-spring Hessians (the transverse part clamped PSD) and an Armijo
line search, pinned vertices on the reference's path - and compares it with RUN/rollout.npz, the
surrogate's own explicit rollout. Usage: python3 tests/thirdparty/implicit_springs.py RUN [SUBSTEPS]
"""
import json, sys, numpy as np
run = sys.argv[1]; fps_div = int(sys.argv[2]) if len(sys.argv) > 2 else 1
j = json.load(open(f'{run}/surrogate.json'))
if j['format'] != 'springtime-surrogate/1':
    sys.exit(f"{run}/surrogate.json is {j['format']}: this script knows springs only")
d = np.load(f'{run}/rollout.npz')
X = d['positions'].reshape(d['positions'].shape[0], -1, 3).astype(np.float64)
pin = d['pinned'].astype(bool)
F, N, _ = X.shape
h = float(d['frame_dt']) / fps_div
S = np.array(j['springs']); a, b = S[:, 0], S[:, 1]
L = np.array(j['rest_length']); k = np.array(j['k']); bd = np.array(j['b'])
m = np.array(j['masses']); c = j['rayleigh']; g = np.array(j['gravity'])
free = ~pin; fi = np.where(free)[0]; idx = -np.ones(N, int); idx[fi] = np.arange(len(fi))

def phi_grad_hess(x, xt, xp, need_h=True):
    dd = x[b] - x[a]; ln = np.linalg.norm(dd, axis=1); u = dd / ln[:, None]
    dp = xp[b] - xp[a]; lp2 = (dp * dp).sum(1)
    ch = dd - dp; al = (ch * dp).sum(1)
    e = (m[:, None] * (x - xt) ** 2).sum() / (2 * h * h) + 0.5 * (k * (ln - L) ** 2).sum() \
        + (bd * al ** 2 / lp2).sum() / (2 * h) + c / (2 * h) * ((x - xp) ** 2).sum() - (m[:, None] * x * g).sum()
    gr = m[:, None] * (x - xt) / (h * h) + c / h * (x - xp) - m[:, None] * g
    fs = (k * (ln - L))[:, None] * u + (bd * al / lp2 / h)[:, None] * dp  # dPhi/d(x_b)
    np.add.at(gr, b, fs); np.add.at(gr, a, -fs)
    if not need_h: return e, gr, None
    n = len(fi); H = np.zeros((3 * n, 3 * n))
    for i in range(n): H[3*i:3*i+3, 3*i:3*i+3] += np.eye(3) * (m[fi[i]] / (h * h) + c / h)
    I = np.eye(3)
    for s in range(len(S)):
        uu = np.outer(u[s], u[s])
        Ks = k[s] * (uu + max(0.0, 1 - L[s] / ln[s]) * (I - uu)) + bd[s] / h * np.outer(dp[s], dp[s]) / lp2[s]
        for p, q, sg in ((a[s], a[s], 1), (b[s], b[s], 1), (a[s], b[s], -1), (b[s], a[s], -1)):
            if free[p] and free[q]:
                H[3*idx[p]:3*idx[p]+3, 3*idx[q]:3*idx[q]+3] += sg * Ks
    return e, gr, H

x2 = X[0].copy(); x1 = X[0].copy(); out = [X[0].copy()]
for f in range(1, F):
    for sub in range(1, fps_div + 1):
        t = (f - 1) + sub / fps_div
        target = X[f - 1][pin] * (1 - sub / fps_div) + X[f][pin] * (sub / fps_div)
        xt = 2 * x1 - x2; x = xt.copy(); x[pin] = target
        for it in range(30):
            e, gr, H = phi_grad_hess(x, xt, x1)
            gf = gr[fi].reshape(-1)
            dx = -np.linalg.solve(H, gf)
            if np.abs(dx).max() < 1e-7: break
            al = 1.0
            while al > 1e-4:
                xn = x.copy(); xn[fi] += al * dx.reshape(-1, 3)
                if phi_grad_hess(xn, xt, x1, False)[0] <= e + 1e-4 * al * gf @ dx: break
                al *= 0.5
            x = xn
        x2, x1 = x1, x
    out.append(x1.copy())
out = np.array(out)
err = np.sqrt(((out - X) ** 2).sum(-1).mean(-1))
T = F // 2
print(f'{run} implicit Euler full space, h = {h*1e3:.2f} ms: RMSE frames {T}-{F}: {1e3*np.sqrt((err[T:]**2).mean()):.1f} mm, '
      f'frames 0-{T}: {1e3*np.sqrt((err[:T]**2).mean()):.1f} mm, max {1e3*np.sqrt(((out-X)**2).sum(-1)).max():.0f} mm')
v = lambda Y: (np.diff(Y[T:], axis=0) ** 2).sum()
print('kinetic energy ratio (unseen half)', v(out) / v(X))
