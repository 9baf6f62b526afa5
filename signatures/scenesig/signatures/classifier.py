"""The classifiers of the scene-signature mining: linear SVMs and their Platt calibration.

McManus et al. 2015, §3.2: each candidate shape's patches train a linear SVM against local negatives
(:class:`LinearSVMTrainer`, the dual on a precomputed linear kernel, :func:`svm_dual`); a survivor's
scores are turned into the detection probability λ of eq. 5 by Platt scaling (:func:`platt`).  The
iterative discriminative clustering that calls them is :mod:`scenesig.signatures.mining`.
"""
from __future__ import annotations

import numpy as np

__all__ = ["svm_dual", "LinearSVMTrainer", "platt", "sigmoid"]


def sigmoid(z):
    """The logistic function of Platt scaling (:func:`platt`), clipped so that ``exp`` cannot overflow."""
    return 1.0 / (1.0 + np.exp(-np.clip(z, -50, 50)))


def svm_dual(K: np.ndarray, n_pos: int, C: float, w_pos: float) -> tuple[np.ndarray, float]:
    """Binary C-SVM on a precomputed kernel (positives first): dual coefficients and bias.

    Returns ``coef`` (n,) and ``b`` with decision ``f(x) = sum_i coef_i k(x_i, x) + b``.
    This is scikit-learn's libsvm binding, called directly: ``SVC.fit`` spends ~2.5 ms per call
    on input validation, ten times the solve itself, and mining makes thousands of fits.  The
    result equals ``SVC(kernel="precomputed", C=C, class_weight={1: w_pos, -1: 1})`` (checked by
    the test suite); if the private binding is unavailable the public estimator is used.
    """
    n = K.shape[0]
    y01 = np.zeros(n)
    y01[:n_pos] = 1.0
    try:
        from sklearn.svm import _libsvm
        _libsvm.set_verbosity_wrap(0)
        support, _, _, dual, intercept, *_ = _libsvm.fit(
            np.ascontiguousarray(K, dtype=np.float64), y01, svm_type=0, kernel="precomputed",
            C=C, class_weight=np.array([1.0, w_pos]), sample_weight=np.empty(0), tol=1e-3,
            cache_size=100.0, max_iter=-1, random_seed=0)
        coef = np.zeros(n)
        # libsvm's sign convention for two classes is the reverse of SVC's public one.
        coef[support] = -dual[0]
        return coef, -float(intercept[0])
    except (ImportError, TypeError, AttributeError):   # pragma: no cover - other sklearn builds
        from sklearn.svm import SVC
        svm = SVC(kernel="precomputed", C=C, class_weight={1.0: w_pos, 0.0: 1.0}, tol=1e-3)
        svm.fit(K, y01)
        coef = np.zeros(n)
        coef[svm.support_] = svm.dual_coef_[0]
        return coef, float(svm.intercept_[0])


class LinearSVMTrainer:
    """SVM fits on the precomputed linear kernel with a cached negative Gram matrix.

    A shape's fits reuse a few negative sets (one per partition, and their unions for the final
    fits): each set's rows and Gram block are gathered once and kept, keyed by the index array
    (callers pass the same array objects again).
    """

    def __init__(self, xc: np.ndarray, xneg: np.ndarray, C: float, balanced: bool):
        self.xc, self.xneg = xc, xneg
        self.gnn = xneg @ xneg.T
        self.C, self.balanced = C, balanced
        self._sets: dict[int, tuple] = {}

    def _negative_set(self, neg_idx):
        got = self._sets.get(id(neg_idx))
        if got is None or got[0] is not neg_idx:
            got = self._sets[id(neg_idx)] = (neg_idx, self.xneg[neg_idx],
                                             self.gnn[np.ix_(neg_idx, neg_idx)].astype(np.float64))
        return got[1], got[2]

    def fit(self, pos_idx, neg_idx):
        """Train on candidate rows ``pos_idx`` vs negative-pool rows ``neg_idx`` -> (w, b)."""
        xp = self.xc[pos_idx]
        xn, gnn = self._negative_set(neg_idx)
        n_p, n_n = len(pos_idx), len(neg_idx)
        K = np.empty((n_p + n_n, n_p + n_n))
        K[:n_p, :n_p] = xp @ xp.T
        kpn = xp @ xn.T
        K[:n_p, n_p:] = kpn
        K[n_p:, :n_p] = kpn.T
        K[n_p:, n_p:] = gnn
        coef, b = svm_dual(K, n_p, self.C, n_n / n_p if self.balanced else 1.0)
        w = coef[:n_p].astype(np.float32) @ xp + coef[n_p:].astype(np.float32) @ xn
        return w, b


def platt(scores: np.ndarray, labels: np.ndarray, C: float) -> tuple[float, float]:
    """Platt scaling: ``p = sigmoid(a * score + b)`` fitted by Newton's method.

    Platt's (1999) smoothed targets ``(N+ + 1) / (N+ + 2)`` and ``1 / (N- + 2)`` keep the fit
    finite when held-out scores separate perfectly; the classes are weighted to equal total mass
    (so lambda = 0.5 where a firing is as likely a signature as not, whatever the sampling ratio of
    negatives to positives), and ``a`` gets a weak ridge penalty ``1 / (2 C)``.  Two parameters
    do not justify scikit-learn's per-call overhead (~50 ms with L-BFGS).
    """
    s = np.asarray(scores, dtype=float)
    y = np.asarray(labels, dtype=float)
    n_pos, n_neg = float(y.sum()), float(len(y) - y.sum())
    if n_pos == 0 or n_neg == 0:
        return (1.0, 0.0)
    t = np.where(y > 0, (n_pos + 1) / (n_pos + 2), 1.0 / (n_neg + 2))
    wt = np.where(y > 0, 0.5 / n_pos, 0.5 / n_neg)
    X = np.stack([s, np.ones_like(s)], axis=1)
    reg = np.diag([1.0 / (2.0 * C * len(s)), 0.0])
    theta = np.array([1.0 / (np.std(s) + 1e-9), -np.mean(s) / (np.std(s) + 1e-9)])

    def objective(th):
        z = X @ th
        # Weighted cross-entropy with soft targets, in a numerically stable form.
        ll = np.logaddexp(0.0, z) - t * z
        return float(np.sum(wt * ll) + 0.5 * th @ reg @ th)

    f = objective(theta)
    for _ in range(100):
        p = 1.0 / (1.0 + np.exp(-np.clip(X @ theta, -50, 50)))
        g = X.T @ (wt * (p - t)) + reg @ theta
        H = (X * (wt * p * (1 - p))[:, None]).T @ X + reg + 1e-10 * np.eye(2)
        step = np.linalg.solve(H, g)
        # Backtracking line search (Platt / Lin et al. 2007): full Newton steps overshoot when
        # the held-out scores are (nearly) separable and the Hessian is tiny.
        lam = 1.0
        while lam > 1e-10:
            cand = theta - lam * step
            fc = objective(cand)
            if fc <= f + 1e-4 * lam * float(g @ (-step)) or fc < f:
                break
            lam *= 0.5
        theta, f_old, f = cand, f, fc
        if abs(f_old - f) < 1e-12 or np.max(np.abs(lam * step)) < 1e-9:
            break
    return float(theta[0]), float(theta[1])
