"""The GP's hyperparameter search, in fewer operations: scikit-learn's
``GaussianProcessRegressor`` with its log marginal likelihood's gradient computed directly.

The marginal-likelihood search (L-BFGS-B) evaluates the likelihood and its gradient tens of times
per fit, and each evaluation costs an (n, n) kernel matrix with its (n, n, p) gradient and an
inverse of the matrix. scikit-learn builds the gradient node by node of the kernel's expression
(stacking arrays at every sum and product, a full (n, n) array for every constant) and forms the
inverse by solving against the identity. :class:`Regressor` computes the same numbers with fewer
passes over (n, n) arrays:

* the kernel and its gradient in one walk of the expression that writes each node's gradient
  into its slice of one preallocated array (:func:`kernel_and_gradient`), with a constant
  factor applied as a scalar and the Matérn and RBF terms computed from the inputs' squared
  differences, which do not depend on the hyperparameters and are computed once per fit (and
  a periodic term of fixed period from ``sin^2(pi |x - x'| / period)``, likewise);
* the gradient of the log marginal likelihood, summed over the outputs ``Y`` (n, m) with
  ``alpha = K^-1 Y``, as one matrix ``W = alpha alpha^T - m K^-1`` (``K^-1`` from the Cholesky
  factor, LAPACK ``potri``) against the gradient read as an (n^2, p) matrix:
  ``d lml / d theta_k = 0.5 sum_ij W_ij dK_ij / d theta_k`` (Rasmussen & Williams, eq. 5.9).

The value of the likelihood is scikit-learn's; the gradient and the kernel equal its to rounding
(tests/test_gp.py compares them on every kernel structure heliocal fits). A kernel with a node
this module does not know (or a fixed hyperparameter) is evaluated by scikit-learn as before.
Prediction is scikit-learn's throughout. What it saves (a GP fit in 0.49x the time) and what
it changes (nothing measurable): docs/experiments/sweep-update-cost.md, twelfth session.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.linalg
import scipy.linalg.lapack
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import (RBF, ConstantKernel, ExpSineSquared, Hyperparameter,
                                              Kernel, Matern, Product, Sum, WhiteKernel)

__all__ = ["OnColumns", "Regressor", "kernel_and_gradient", "walks"]


class OnColumns(Kernel):
    """scikit-learn's kernels act on every input column; this one applies ``kernel`` to the
    columns ``columns`` only (the sun angles, the time, the env columns)."""

    def __init__(self, kernel, columns):
        self.kernel = kernel
        self.columns = columns

    def get_params(self, deep=True):
        params = dict(kernel=self.kernel, columns=self.columns)
        if deep:
            params.update(("kernel__" + k, v) for k, v in self.kernel.get_params().items())
        return params

    @property
    def hyperparameters(self):
        return [Hyperparameter("kernel__" + h.name, h.value_type, h.bounds, h.n_elements)
                for h in self.kernel.hyperparameters]

    @property
    def theta(self):
        return self.kernel.theta

    @theta.setter
    def theta(self, theta):
        self.kernel.theta = theta

    @property
    def bounds(self):
        return self.kernel.bounds

    def __eq__(self, other):
        return (type(self) is type(other) and self.kernel == other.kernel
                and tuple(self.columns) == tuple(other.columns))

    def _take(self, x):
        return None if x is None else np.asarray(x)[:, list(self.columns)]

    def __call__(self, X, Y=None, eval_gradient=False):
        return self.kernel(self._take(X), self._take(Y), eval_gradient=eval_gradient)

    def diag(self, X):
        return self.kernel.diag(self._take(X))

    def is_stationary(self):
        return self.kernel.is_stationary()

    def __repr__(self):
        return f"{self.kernel!r} on {list(self.columns)}"


# ------------------------------------------------------------------------------------------------
# the kernel and its gradient in one walk
# ------------------------------------------------------------------------------------------------
class _Unknown(Exception):
    """A kernel node :func:`kernel_and_gradient` does not evaluate itself."""


def _squared_differences(X: np.ndarray, columns: tuple, cache: dict) -> np.ndarray:
    """(d, n, n) squared differences of ``X``'s ``columns`` between every two rows (computed
    once per ``cache``: they do not depend on the hyperparameters)."""
    if columns not in cache:
        x = X[:, list(columns)].T
        cache[columns] = (x[:, :, np.newaxis] - x[:, np.newaxis, :]) ** 2
    return cache[columns]


def _n_params(node) -> int:
    """The number of hyperparameters of a node the walk knows (scikit-learn's ``n_dims``,
    without building its hyperparameter lists)."""
    if isinstance(node, OnColumns):
        return _n_params(node.kernel)
    if isinstance(node, (Sum, Product)):
        return _n_params(node.k1) + _n_params(node.k2)
    if isinstance(node, (ConstantKernel, WhiteKernel)):
        return 1
    if type(node) is RBF or (type(node) is Matern and node.nu in _MATERN_NU):
        return np.size(node.length_scale) if node.anisotropic else 1
    if _fixed_period(node):
        return 1
    raise _Unknown(node)


def _fixed_period(node) -> bool:
    """An ``ExpSineSquared`` whose period is held fixed (its length the one hyperparameter)."""
    return (type(node) is ExpSineSquared and isinstance(node.periodicity_bounds, str)
            and node.periodicity_bounds == "fixed"
            and not (isinstance(node.length_scale_bounds, str)
                     and node.length_scale_bounds == "fixed"))


def _periodic(node, columns: tuple, X, G, cache) -> np.ndarray:
    """``ExpSineSquared`` of fixed period on one column: ``K = exp(-2 S / l^2)`` with ``S =
    sin^2(pi |x - x'| / period)`` (computed once per ``cache``), its gradient by ``log l``,
    ``4 K S / l^2``, into ``G[0]``."""
    key = ("periodic", columns, float(node.periodicity))
    if key not in cache:
        d = np.sqrt(_squared_differences(X, columns, cache).sum(0))
        cache[key] = np.sin(np.pi * d / node.periodicity) ** 2
    S = cache[key]
    l2 = float(node.length_scale) ** 2
    K = np.exp(-2.0 * S / l2)
    np.multiply(K, 4.0 * S / l2, out=G[0])
    return K


#: The Matérn smoothness values with a closed form (scikit-learn's others need Bessel functions).
_MATERN_NU = (0.5, 1.5, 2.5, math.inf)


def _stationary(node, columns: tuple, X, G, cache) -> np.ndarray:
    """A Matérn (nu 0.5, 1.5, 2.5) or RBF kernel on ``columns``: K, its gradient by the log
    length scales into ``G`` (one (n, n) slice per length, or one for an isotropic length)."""
    length = np.atleast_1d(np.asarray(node.length_scale, dtype=float))
    D = _squared_differences(X, columns, cache) / (length ** 2)[:, np.newaxis, np.newaxis]
    r2 = D.sum(0)
    nu = node.nu if isinstance(node, Matern) else math.inf
    if nu == 0.5:
        r = np.sqrt(r2)
        K = np.exp(-r)
        with np.errstate(invalid="ignore", divide="ignore"):
            factor = np.where(r > 0, K / r, 0.0)
    elif nu == 1.5:
        s = np.sqrt(3 * r2)
        e = np.exp(-s)
        K = (1.0 + s) * e
        factor = 3 * e
    elif nu == 2.5:
        s = np.sqrt(5 * r2)
        e = np.exp(-s)
        K = (1.0 + s + s ** 2 / 3.0) * e
        factor = 5.0 / 3.0 * ((s + 1) * e)
    elif nu == math.inf:
        K = np.exp(-r2 / 2.0)
        factor = K
    else:
        raise _Unknown(node)
    if len(G) == 1:          # an isotropic length: the sum over the columns
        np.multiply(r2, factor, out=G[0])
    else:
        np.multiply(D, factor, out=G)
    return K


def _walk(node, X, G, cache, columns=None) -> np.ndarray:
    """K of ``node`` on the rows ``X``; its gradient by ``node``'s log hyperparameters written
    into ``G`` (node's number of hyperparameters, n, n)."""
    if isinstance(node, OnColumns):
        return _walk(node.kernel, X, G, cache, tuple(node.columns))
    if isinstance(node, (Sum, Product)):
        if isinstance(node, Product) and isinstance(node.k1, ConstantKernel):
            c = node.k1.constant_value       # a factor: scaled, not multiplied as a matrix
            K = c * _walk(node.k2, X, G[1:], cache, columns)
            G[1:] *= c
            G[0] = K
            return K
        p1 = _n_params(node.k1)
        K1 = _walk(node.k1, X, G[:p1], cache, columns)
        K2 = _walk(node.k2, X, G[p1:], cache, columns)
        if isinstance(node, Sum):
            return K1 + K2
        G[:p1] *= K2
        G[p1:] *= K1
        return K1 * K2
    if isinstance(node, ConstantKernel):
        G[0] = node.constant_value
        return np.full(G.shape[1:], node.constant_value, dtype=float)
    if isinstance(node, WhiteKernel):
        K = node.noise_level * np.eye(len(X))
        G[0] = K
        return K
    if type(node) in (Matern, RBF):
        return _stationary(node, columns if columns is not None else tuple(range(X.shape[1])),
                           X, G, cache)
    if _fixed_period(node):
        return _periodic(node, columns if columns is not None else tuple(range(X.shape[1])),
                         X, G, cache)
    raise _Unknown(node)


def walks(kernel) -> bool:
    """Whether :func:`kernel_and_gradient` evaluates ``kernel`` itself: every node one it
    knows, no hyperparameter fixed but a periodic term's period."""
    try:
        _n_params(kernel)
    except _Unknown:
        return False
    return not any(h.fixed for h in kernel.hyperparameters
                   if not h.name.endswith("periodicity"))


def _walked(kernel, X: np.ndarray, cache: dict) -> tuple[np.ndarray, np.ndarray]:
    """K (n, n) and its gradient by the log hyperparameters, parameter first (p, n, n)."""
    G = np.empty((_n_params(kernel), len(X), len(X)))
    return _walk(kernel, X, G, cache), G


def kernel_and_gradient(kernel, X: np.ndarray, cache: dict | None = None):
    """``kernel(X, eval_gradient=True)``: K (n, n) and its gradient by the log hyperparameters
    (n, n, p), in one walk of the kernel's expression (module docstring); scikit-learn's own call
    for a kernel it does not :func:`walk <walks>`. ``cache``: a dict kept across calls on the
    same ``X`` (the squared differences)."""
    if not walks(kernel):
        return kernel(X, eval_gradient=True)
    K, G = _walked(kernel, np.asarray(X, dtype=float), {} if cache is None else cache)
    return K, np.moveaxis(G, 0, -1)


# ------------------------------------------------------------------------------------------------
# the regressor
# ------------------------------------------------------------------------------------------------
class Regressor(GaussianProcessRegressor):
    """scikit-learn's regressor whose hyperparameter search evaluates the log marginal
    likelihood's gradient as the module docstring says (the same optimum; the optimizer's path
    can differ in the last bits)."""

    def log_marginal_likelihood(self, theta=None, eval_gradient=False, clone_kernel=True):
        if theta is None or not eval_gradient:
            return super().log_marginal_likelihood(theta, eval_gradient, clone_kernel)
        if clone_kernel:
            kernel = self.kernel_.clone_with_theta(theta)
        else:
            kernel = self.kernel_
            kernel.theta = theta
        if getattr(self, "_walk_of", None) is not self.X_train_:   # a new fit: its scratch
            self._walk_of, self._differences = self.X_train_, {}
            self._walks = walks(kernel)
        if self._walks:
            K, K_gradient = _walked(kernel, self.X_train_, self._differences)
        else:
            K, K_gradient = kernel(self.X_train_, eval_gradient=True)
            K_gradient = np.moveaxis(K_gradient, -1, 0)
        K[np.diag_indices_from(K)] += self.alpha
        try:
            L = scipy.linalg.cholesky(K, lower=True, check_finite=False)
        except np.linalg.LinAlgError:
            return -np.inf, np.zeros_like(theta)
        y = self.y_train_.reshape(len(K), -1)
        alpha = scipy.linalg.cho_solve((L, True), y, check_finite=False)
        n, m = y.shape
        lml = (-0.5 * np.einsum("ik,ik->k", y, alpha) - np.log(np.diag(L)).sum()
               - n / 2 * np.log(2 * np.pi)).sum()
        k_inv, info = scipy.linalg.lapack.dpotri(L, lower=1)
        if info != 0:   # not expected after a successful Cholesky; scikit-learn's way then
            return super().log_marginal_likelihood(theta, eval_gradient, clone_kernel)
        k_inv = np.tril(k_inv) + np.tril(k_inv, -1).T      # potri fills the lower triangle
        weights = alpha @ alpha.T - m * k_inv
        return lml, 0.5 * (K_gradient.reshape(len(K_gradient), n * n) @ weights.reshape(-1))

    def __getstate__(self):
        state = dict(self.__dict__)
        for scratch in ("_walk_of", "_differences", "_walks"):   # a fit's, not the model
            state.pop(scratch, None)
        return state
