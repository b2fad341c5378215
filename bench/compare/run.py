#!/usr/bin/env python3
"""The other tools on the problems Helmholtz exports (`helmholtz-bench --preset compare`).

Runs, on every exported problem (DIR/NAME/problem.json + NPY files, see
server/src/bench/compare.rs for the conventions):

- pylops FISTA, l1 on orthonormal Daubechies-4 wavelet coefficients (pylops DWT2D, periodised);
- pyproximal primal-dual (Chambolle-Pock) isotropic TV with t >= 0 (pyproximal.Box);
- for Hadamard problems, spyrit's fast pseudo-inverse (HadamSplit2d + PinvNet, which is the
  zero-filled inverse for a subset of rows), if spyrit imports.

Each regularised solver sweeps its weight over a grid (extended while the best point, by
ground-truth MSE, sits at an edge, by one point); the best point is re-timed (--repeat, median). Every
reconstruction is written as NPY with its solve time to OUT/results.json; the Rust side scores
them all with the service's own PSNR/SSIM and keeps each solver's best by PSNR (the same point:
PSNR is a decreasing function of the MSE for a fixed truth).

Starts itself in a venv under target/compare-venv (created, and requirements installed, on first
use; never a global install).
"""

import argparse
import hashlib
import importlib.metadata
import json
import os
import pathlib
import platform
import subprocess
import sys
import time

HERE = pathlib.Path(__file__).resolve().parent
ROOT = HERE.parent.parent
VENV = ROOT / "target" / "compare-venv"
REQUIREMENTS = HERE / "requirements.txt"
REQUIREMENTS_SPYRIT = HERE / "requirements-spyrit.txt"


def ensure_venv():
    """Re-executes this script in the venv (creating it and installing the pins if needed)."""
    if pathlib.Path(sys.prefix).resolve() == VENV.resolve():
        return
    py = VENV / "bin" / "python"
    if not py.exists():
        print(f"run.py: creating the venv {VENV}", file=sys.stderr)
        subprocess.check_call([sys.executable, "-m", "venv", str(VENV)])
    want = hashlib.sha256(REQUIREMENTS.read_bytes() + REQUIREMENTS_SPYRIT.read_bytes()).hexdigest()
    stamp = VENV / ".helmholtz-requirements"
    if not stamp.exists() or stamp.read_text().split()[0] != want:
        print("run.py: installing bench/compare/requirements.txt into the venv", file=sys.stderr)
        subprocess.check_call([str(py), "-m", "pip", "install", "-q", "-r", str(REQUIREMENTS)])
        # spyrit needs torch (several GB with its CUDA libraries from PyPI); optional.
        print("run.py: installing bench/compare/requirements-spyrit.txt (torch) into the venv", file=sys.stderr)
        rc = subprocess.call([str(py), "-m", "pip", "install", "-q", "-r", str(REQUIREMENTS_SPYRIT)])
        stamp.write_text(f"{want} spyrit-install-exit-code={rc}\n")
    os.execv(str(py), [str(py), str(pathlib.Path(__file__).resolve())] + sys.argv[1:])


ensure_venv()

import numpy as np  # noqa: E402
import pylops  # noqa: E402
import pyproximal  # noqa: E402

try:
    import torch
    import spyrit
    import spyrit.core.meas as spymeas
    import spyrit.core.prep as spyprep
    import spyrit.core.recon as spyrecon

    SPYRIT_ERROR = None
except Exception as e:  # noqa: BLE001 - any import failure means: not available here
    SPYRIT_ERROR = f"{type(e).__name__}: {e}"


def fwht(a):
    """Unnormalised natural-order (Sylvester) fast Walsh-Hadamard transform of a 1D array."""
    a = np.asarray(a, dtype=np.float64)
    k = a.size
    h = 1
    while h < k:
        a = a.reshape(-1, 2, h)
        a = np.stack((a[:, 0] + a[:, 1], a[:, 0] - a[:, 1]), axis=1)
        h *= 2
    return a.reshape(k)


class HadamardSubset(pylops.LinearOperator):
    """A[r, p] = (-1)^popcount(natural[r] & p) / sqrt(k): the exported convention, by FWHT.

    pylops has no Walsh-Hadamard operator; this wraps numpy code in pylops' interface (dense
    pylops.MatrixMult would be ~k/log2(k) times more work per product).
    """

    def __init__(self, natural, k):
        self.natural = np.asarray(natural, dtype=np.int64)
        self.k = k
        self.scale = 1.0 / np.sqrt(k)
        super().__init__(dtype=np.dtype("float64"), shape=(len(self.natural), k))

    def _matvec(self, x):
        return fwht(x)[self.natural] * self.scale

    def _rmatvec(self, y):
        z = np.zeros(self.k)
        z[self.natural] = y
        return fwht(z) * self.scale


class DenseF32(pylops.LinearOperator):
    """The exported 0/1 matrix as float32 (exact), products in float32 (half the memory traffic of
    float64; pylops.MatrixMult on a float32 matrix would upcast it on every float64 product)."""

    def __init__(self, a):
        self.a = np.ascontiguousarray(a, dtype=np.float32)
        super().__init__(dtype=np.dtype("float64"), shape=self.a.shape)

    def _matvec(self, x):
        return (self.a @ x.astype(np.float32)).astype(np.float64)

    def _rmatvec(self, y):
        return (y.astype(np.float32) @ self.a).astype(np.float64)


class Problem:
    def __init__(self, d):
        self.dir = d
        self.m = json.loads((d / "problem.json").read_text())
        self.name = self.m["name"]
        self.w, self.h = self.m["width"], self.m["height"]
        self.k = self.w * self.h
        self.truth = np.load(d / self.m["truth"]).astype(np.float64)
        self.b = np.load(d / self.m["b"])
        op = self.m["operator"]
        self.kind = op["kind"]
        if self.kind == "dense":
            # float32 products (the matrix is 0/1: exact); BLAS at its default threads.
            self.op = DenseF32(np.load(d / op["matrix"]))
            self.dtype = np.float64
        elif self.kind == "hadamard_subset":
            self.natural = np.load(d / op["natural"])
            self.frames = np.load(d / op["frames"])
            self.op = HadamardSubset(self.natural, self.k)
            self.dtype = np.float64
        else:
            raise SystemExit(f"{d}: unknown operator kind {self.kind}")
        # The exported operator applied to the truth must give the exported data.
        err = np.max(np.abs(self.op @ self.truth.ravel().astype(self.dtype) - self.b)) / max(np.max(np.abs(self.b)), 1e-30)
        if err > 1e-4:
            raise SystemExit(f"{self.name}: A t differs from b by {err:.2e} (relative): convention mismatch")

    def mse(self, x):
        return float(np.mean((np.asarray(x, dtype=np.float64).reshape(self.h, self.w) - self.truth) ** 2))


def op_norm(op, dtype, iters=30, seed=0):
    """||op||_2 by power iteration on op^T op."""
    rng = np.random.default_rng(seed)
    x = rng.standard_normal(op.shape[1]).astype(dtype)
    x /= np.linalg.norm(x)
    s = 0.0
    for _ in range(iters):
        y = op.H @ (op @ x)
        s = np.linalg.norm(y)
        x = (y / s).astype(dtype)
    return float(np.sqrt(s))


# ---- the solvers: each returns (image, iterations, convergence text, params) ----


def wavelet_level(n):
    # Coarsest approximation 8 x 8 (pylops' default, 1 level, would barely sparsify).
    return max(1, int(np.log2(n)) - 3)


def fista_wavelets(p, frac, niter):
    """pylops FISTA: min 1/2 ||A W^T z - b||^2 + eps ||z||_1 (pylops' convention), image W^T z."""
    W = pylops.signalprocessing.DWT2D(dims=(p.h, p.w), wavelet="db4", level=wavelet_level(min(p.h, p.w)), dtype=p.dtype)
    Op = p.op @ W.H
    # z = 0 is optimal for eps >= 2 ||Op^T b||_inf in pylops' scaling (threshold eps * alpha / 2).
    eps = frac * 2.0 * float(np.max(np.abs(Op.H @ p.b)))
    z, iters, _cost = pylops.optimization.sparsity.fista(Op, p.b, niter=niter, eps=eps, tol=1e-7, show=False)
    x = W.H @ z
    conv = "stopped by tol (model update < 1e-7)" if iters < niter else f"ran the cap of {niter} iterations"
    params = {"wavelet": "db4", "levels": wavelet_level(min(p.h, p.w)), "eps_fraction": frac, "eps": eps}
    return x, int(iters), conv, params


def tv_primal_dual(p, frac, niter):
    """pyproximal PrimalDual: min 1/2 ||A t - b||^2 / s^2 + lam TV(t) s.t. t >= 0.

    The stacked operator [A / s; grad] (s = ||A||, found by power iteration inside the timed
    solve) keeps the step sizes balanced: tau = mu = 0.99 / sqrt(1 + 8).
    """
    s = 1.0 if p.kind == "hadamard_subset" else op_norm(p.op, p.dtype)
    As = (1.0 / s) * p.op
    bs = (p.b / s).astype(p.dtype)
    G = pylops.Gradient(dims=(p.h, p.w), edge=True, kind="forward", dtype=p.dtype)
    lam = frac * float(np.max(np.abs(As.H @ bs)))
    K = pylops.VStack([As, G])
    g = pyproximal.VStack([pyproximal.L2(b=bs), pyproximal.L21(ndim=2, sigma=lam)], nn=[As.shape[0], G.shape[0]])
    f = pyproximal.Box(lower=0.0)
    step = 0.99 / np.sqrt(1.0 + 8.0)
    x = pyproximal.optimization.primaldual.PrimalDual(
        f, g, K, x0=np.zeros(p.k, dtype=p.dtype), tau=step, mu=step, theta=1.0, niter=niter, show=False
    )
    params = {"lambda_fraction": frac, "lambda_scaled": lam, "norm_A": s, "tau": step, "mu": step}
    return x, niter, f"fixed {niter} iterations", params


def spyrit_pinv(p):
    """spyrit HadamSplit2d + PinvNet(Unsplit, use_fast_pinv): the zero-filled inverse."""
    h = p.h
    m = len(p.natural)
    net, y = p.spyrit_state
    with torch.no_grad():
        x = net.reconstruct_pinv(y)
    return x.reshape(h, h).numpy().astype(np.float64), 1, "direct (no iterations)", {"M": m, "prep": "Unsplit", "use_fast_pinv": True}


def spyrit_setup(p):
    """spyrit's operator with our rows first, checked against the exported frames."""
    h = p.h
    if p.w != p.h:
        raise RuntimeError("spyrit's HadamSplit2d is square only")
    bits = int(np.log2(h))

    def bitrev(x):
        return int(format(x, f"0{bits}b")[::-1], 2) if bits else 0

    # spyrit's Walsh (sequency) index s <-> our natural (Sylvester) index bitrev(gray(s)).
    seq_of_nat = np.zeros(h, dtype=np.int64)
    for s in range(h):
        seq_of_nat[bitrev(s ^ (s >> 1))] = s
    m = len(p.natural)
    order = torch.zeros(h, h, dtype=torch.float64)
    for r, n in enumerate(p.natural):
        u, v = divmod(int(n), p.w)
        order[seq_of_nat[u], seq_of_nat[v]] = float(2 * m - r)  # highest first: our order
    meas = spymeas.HadamSplit2d(h, m, order=order)
    net = spyrecon.PinvNet(meas, spyprep.Unsplit(), use_fast_pinv=True, reshape_output=True)
    y = torch.tensor(p.frames, dtype=torch.float32).reshape(1, 1, -1)
    with torch.no_grad():
        sim = meas.measure(torch.tensor(p.truth, dtype=torch.float32).reshape(1, 1, h, h)).reshape(-1).numpy()
    err = np.max(np.abs(sim.astype(np.float64) - p.frames)) / np.max(np.abs(p.frames))
    if err > 1e-4:
        raise RuntimeError(f"spyrit's split frames differ from the exported ones by {err:.2e} (relative)")
    return net, y


def timed(fn, *args):
    t0 = time.perf_counter()
    out = fn(*args)
    return out, time.perf_counter() - t0


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--problems", required=True, type=pathlib.Path)
    ap.add_argument("--out", required=True, type=pathlib.Path)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--only", help="comma-separated problem names")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    def version(dist):
        try:
            return importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            return None

    env = {"python": platform.python_version()}
    for dist in ["numpy", "scipy", "PyWavelets", "pylops", "pyproximal", "spyrit", "torch"]:
        env[dist.lower()] = version(dist) if dist not in ("spyrit", "torch") or not SPYRIT_ERROR else None
    env["torch_threads"] = None if SPYRIT_ERROR else torch.get_num_threads()
    notes = []
    if SPYRIT_ERROR:
        notes.append(f"spyrit not available: {SPYRIT_ERROR}")
    runs = []

    def record(p, tool, method, params, iters, conv, x, seconds, all_seconds, tag, extra=None):
        rel = f"{p.name}/{tool}-{method.replace(' ', '_')}-{tag}.npy"
        np.save(args.out / rel, np.asarray(x, dtype=np.float64).reshape(p.h, p.w).astype(np.float32))
        run = {
            "problem": p.name, "tool": tool, "method": method, "params": params, "iterations": iters,
            "convergence": conv, "seconds": seconds, "all_seconds": all_seconds, "image": rel,
        }
        run.update(extra or {})
        runs.append(run)
        return run

    def sweep(p, tool, method, solve, grid, niter, step=3.0):
        """Solves on the grid, extending it (by 1 more point) while the best MSE is at an edge."""
        fracs = list(grid)
        done = {}
        while True:
            for f in fracs:
                if f not in done:
                    (x, iters, conv, params), sec = timed(solve, p, f, niter)
                    done[f] = (p.mse(x), x, iters, conv, params, sec)
                    print(f"  {p.name} {tool} {method} weight {f:.1e}: MSE {done[f][0]:.3e}, {iters} it, {sec:.2f} s", file=sys.stderr, flush=True)
            keys = sorted(done)
            best = min(keys, key=lambda f: done[f][0])
            if len(keys) >= len(grid) + 1 or best not in (keys[0], keys[-1]):
                break
            fracs = [keys[0] / step] if best == keys[0] else [keys[-1] * step]
        sweep_seconds = sum(v[5] for v in done.values())
        # Re-time the best point (the median of --repeat runs) when a solve is short; solves of
        # more than 5 s are timed once (their run-to-run spread is small against their length).
        times = [done[best][5]]
        for _ in range(max(0, args.repeat - 1) if done[best][5] < 5.0 else 0):
            _, sec = timed(solve, p, best, niter)
            times.append(sec)
        for f in keys:
            mse, x, iters, conv, params, sec = done[f]
            all_s = sorted(times) if f == best else [sec]
            med = all_s[len(all_s) // 2]
            record(p, tool, method, params, iters, conv, x, med, all_s, f"w{f:.0e}",
                   {"timed_best": f == best, "sweep_seconds": sec})
        # Convergence check at the best weight: twice the iterations (not timed in the table).
        x3, iters3, _, params3 = solve(p, best, 2 * niter)
        record(p, tool, method, params3, iters3, "convergence check", x3, None, [], "check",
               {"role": "convergence_check", "check_of": f"w{best:.0e}"})

    problems = sorted(d for d in args.problems.iterdir() if (d / "problem.json").exists())
    if args.only:
        keep = set(args.only.split(","))
        problems = [d for d in problems if d.name in keep]
    for d in problems:
        p = Problem(d)
        (args.out / p.name).mkdir(parents=True, exist_ok=True)
        print(f"run.py: {p.name} ({p.kind}, {p.op.shape[0]} rows x {p.k} pixels)", file=sys.stderr, flush=True)
        hadamard = p.kind == "hadamard_subset"
        if hadamard and not SPYRIT_ERROR:
            try:
                p.spyrit_state = spyrit_setup(p)
                spyrit_pinv(p)  # one untimed warm-up call
                times = []
                for _ in range(max(1, args.repeat)):
                    (x, iters, conv, params), sec = timed(spyrit_pinv, p)
                    times.append(sec)
                times.sort()
                record(p, "spyrit", "fast pseudo-inverse (zero-filled)", params, iters, conv, x, times[len(times) // 2], times, "pinv",
                       {"timed_best": True, "note": "after one untimed warm-up call"})
            except RuntimeError as e:
                notes.append(f"{p.name}: spyrit refused: {e}")
        # Iterations (each checked at twice as many, untimed): orthonormal Hadamard rows converge
        # in a few hundred. 0/1 Bernoulli rows have a large common mode (||A|| ~ 30x the other
        # singular values), which slows both solvers; their products with the dense matrix are the
        # cost of an iteration (~50 ms at 128 x 128, ~150 ms at 256 x 256 here), so they are
        # capped at 500 and 300 iterations to keep the whole sweep within minutes.
        if hadamard:
            n_pd, n_fista = 500, 200
        else:
            n_pd = n_fista = 500 if p.op.shape[0] * p.k <= 3e7 else 300
        sweep(p, "pyproximal", "primal-dual TV, t >= 0", tv_primal_dual, [3e-3, 1e-2, 3e-2], n_pd)
        sweep(p, "pylops", "FISTA l1 on db4 wavelets", fista_wavelets, [1e-4, 1e-3, 1e-2], n_fista)
    env["notes"] = notes
    env["blas"] = blas_name()
    (args.out / "results.json").write_text(json.dumps({"environment": env, "runs": runs}, indent=1, allow_nan=False))
    print(f"run.py: wrote {args.out / 'results.json'}", file=sys.stderr)


def blas_name():
    try:
        cfg = np.show_config(mode="dicts")
        blas = cfg["Build Dependencies"]["blas"]
        return f"{blas.get('name')} {blas.get('version')}"
    except Exception:  # noqa: BLE001
        return "?"


if __name__ == "__main__":
    main()
