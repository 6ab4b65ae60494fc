"""Test oracle: scikit-learn reference of the hypotheses stage.

The same recipe as `hypotheses.fit_hypotheses`, one scenario at a time, with
scikit-learn's MinMaxScaler, PCA and GaussianMixture(covariance_type='full') + bic().
To make the two comparable, GaussianMixture starts from the same deterministic
initialisation (farthest-point seeds, nearest-seed hard assignment, one M-step with
the same reg_covar), passed as weights_init / means_init / precisions_init; it then
runs at most `em_iters` EM iterations (tol = 0 runs exactly that many, as the JAX
path does). Only tests import it; the package never imports scikit-learn.
"""

import warnings

import numpy as np
import threadpoolctl
from sklearn import decomposition, exceptions, mixture, preprocessing

from cvmdx_jax.config.sampling import HypothesisConfig


def embed(trajectories: np.ndarray, config: HypothesisConfig) -> np.ndarray:
  """Scaled, flattened, PCA-projected samples of one scenario (scikit-learn).

  Args:
    trajectories: (N, T, 2) positions in metres.
    config: scaling, x_scale, y_scale and pca_dim are used.

  Returns:
    (N, pca_dim) float64 PCA scores.
  """
  trajectories = np.asarray(trajectories, np.float64)
  num_samples = trajectories.shape[0]
  if config.scaling == "minmax":
    scaled = preprocessing.MinMaxScaler().fit_transform(trajectories.reshape(-1, 2))
  else:
    scaled = trajectories / np.array([config.x_scale, config.y_scale])
  flat = scaled.reshape(num_samples, -1)
  return decomposition.PCA(n_components=config.pca_dim, svd_solver="full").fit_transform(flat)


def farthest_point_labels(points: np.ndarray, num_components: int) -> np.ndarray:
  """(N,) nearest-seed labels for greedy farthest-point seeds (first: farthest from mean)."""
  seeds = [int(np.argmax(np.sum((points - points.mean(axis=0)) ** 2, axis=1)))]
  min_dist = np.full(len(points), np.inf)
  for _ in range(num_components - 1):
    min_dist = np.minimum(min_dist, np.sum((points - points[seeds[-1]]) ** 2, axis=1))
    seeds.append(int(np.argmax(min_dist)))
  sq_dist = np.sum((points[:, None, :] - points[seeds][None]) ** 2, axis=-1)
  return np.argmin(sq_dist, axis=1)


def initial_parameters(
    points: np.ndarray, labels: np.ndarray, num_components: int, reg_covar: float
) -> dict:
  """weights_init, means_init, precisions_init of a hard assignment (one M-step)."""
  resp = np.eye(num_components)[labels]
  counts = resp.sum(axis=0) + 10 * np.finfo(np.float64).eps
  means = resp.T @ points / counts[:, None]
  diff = points[None] - means[:, None]
  covs = np.einsum("nk,kni,knj->kij", resp, diff, diff) / counts[:, None, None]
  covs += reg_covar * np.eye(points.shape[1])
  return {
      "weights_init": counts / counts.sum(),
      "means_init": means,
      "precisions_init": np.linalg.inv(covs),
  }


def fit_scenario(
    trajectories: np.ndarray, config: HypothesisConfig, tol: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
  """The recipe for one scenario with scikit-learn.

  Args:
    trajectories: (N, T, 2) positions in metres.
    config: the `HypothesisConfig` to mirror (em_iters >= 1).
    tol: GaussianMixture tol; 0 runs exactly em_iters iterations.

  Returns:
    bic: (c_max,) BIC for C = 1..c_max.
    labels: (N,) component of each sample under the lowest-BIC fit.
  """
  points = embed(trajectories, config)
  bics, labels = [], []
  for num_components in range(1, config.c_max + 1):
    init = initial_parameters(
        points, farthest_point_labels(points, num_components), num_components, config.reg_covar
    )
    model = mixture.GaussianMixture(
        num_components,
        covariance_type="full",
        reg_covar=config.reg_covar,
        tol=tol,
        max_iter=config.em_iters,
        n_init=1,
        init_params="random_from_data",
        random_state=0,
        **init,
    )
    with warnings.catch_warnings():
      warnings.simplefilter("ignore", exceptions.ConvergenceWarning)
      model.fit(points)
    bics.append(model.bic(points))
    labels.append(model.predict(points))
  bics = np.asarray(bics)
  return bics, labels[int(np.argmin(bics))]


def fit_batch(trajectories: np.ndarray, config: HypothesisConfig, tol: float = 0.0) -> np.ndarray:
  """(B, c_max) BIC of every scenario of (B, N, T, 2) trajectories, one at a time.

  BLAS runs single-threaded: on these tiny matrices threads only add overhead
  (17x slower with 2 busy threads on a loaded 2-core machine).
  """
  with threadpoolctl.threadpool_limits(1):
    return np.stack([fit_scenario(t, config, tol)[0] for t in trajectories])
