"""scikit-learn reference of the hypotheses stage, and sample sets with known modes.

The test oracle and the benchmark baseline: the same recipe as
`hypotheses.fit_hypotheses`, one scenario at a time, with scikit-learn's
MinMaxScaler, PCA and GaussianMixture(covariance_type='full') + bic(). To make
the two comparable, GaussianMixture starts from the same deterministic
initialisation (farthest-point seeds, nearest-seed hard assignment, one
M-step with the same reg_covar), passed as weights_init / means_init /
precisions_init; it then runs at most `em_iters` EM iterations (tol = 0 runs
exactly that many, as the JAX path does).

`mode_sets` draws highway-like sets of sampled futures around 1, 2 or 3
well-separated modes (keep lane, lane change left/right by one 3.5 m lane,
keep speed or brake), for checks of agreement and mode recovery.

Only tests and experiments import this module; the library's run-time path
never imports scikit-learn.
"""

import warnings

import numpy as np
import threadpoolctl
from sklearn import decomposition
from sklearn import exceptions
from sklearn import mixture
from sklearn import preprocessing

from cvmdx_jax import constants
from cvmdx_jax.multimodal.hypotheses import HypothesisConfig

LANE_WIDTH = 3.5  # m
# (lateral offset in lanes, braking or not) of each mode kind.
MODE_KINDS = ((0, 0), (1, 0), (-1, 0), (0, 1), (1, 1), (-1, 1))


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


def initial_parameters(points: np.ndarray, labels: np.ndarray, num_components: int,
                       reg_covar: float) -> dict:
  """weights_init, means_init, precisions_init of a hard assignment (one M-step)."""
  resp = np.eye(num_components)[labels]
  counts = resp.sum(axis=0) + 10 * np.finfo(np.float64).eps
  means = resp.T @ points / counts[:, None]
  diff = points[None] - means[:, None]
  covs = np.einsum("nk,kni,knj->kij", resp, diff, diff) / counts[:, None, None]
  covs += reg_covar * np.eye(points.shape[1])
  return {"weights_init": counts / counts.sum(), "means_init": means,
          "precisions_init": np.linalg.inv(covs)}


def fit_scenario(trajectories: np.ndarray, config: HypothesisConfig,
                 tol: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
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
    init = initial_parameters(points, farthest_point_labels(points, num_components),
                              num_components, config.reg_covar)
    model = mixture.GaussianMixture(
        num_components, covariance_type="full", reg_covar=config.reg_covar, tol=tol,
        max_iter=config.em_iters, n_init=1, init_params="random_from_data", random_state=0,
        **init)
    with warnings.catch_warnings():
      warnings.simplefilter("ignore", exceptions.ConvergenceWarning)
      model.fit(points)
    bics.append(model.bic(points))
    labels.append(model.predict(points))
  bics = np.asarray(bics)
  return bics, labels[int(np.argmin(bics))]


def fit_batch(trajectories: np.ndarray, config: HypothesisConfig,
              tol: float = 0.0) -> np.ndarray:
  """(B, c_max) BIC of every scenario of (B, N, T, 2) trajectories, one at a time.

  BLAS runs single-threaded: on these tiny matrices threads only add overhead
  (17x slower with 2 busy threads on a loaded 2-core machine).
  """
  with threadpoolctl.threadpool_limits(1):
    return np.stack([fit_scenario(t, config, tol)[0] for t in trajectories])


def mode_sets(seed: int, num_sets: int, num_samples: int = 9, num_modes=None,
              brake: float = -4.0, num_steps: int = constants.T_PRED,
              dt: float = constants.DT) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """Sets of sampled highway futures around a known number of modes.

  Each set has a speed v0 ~ U(22, 38) m/s and 1-3 distinct mode kinds
  (`MODE_KINDS`: lane offset -1/0/+1 lanes by a smooth 3-4.5 s lane change
  starting within 0.3-1.5 s, acceleration 0 or `brake`), each holding at
  least 2 of the samples. Per sample: speed noise 0.5 m/s, acceleration noise
  0.15 m/s^2, lateral offset noise 0.15 m, lane-change timing jitter 0.15 s,
  and 0.03 m white position noise.

  Args:
    seed: numpy seed.
    num_sets: B.
    num_samples: N per set (>= 2 per mode).
    num_modes: int or (B,) ints in 1..3; default uniform over 1..3.
    brake: acceleration of braking modes, m/s^2.
    num_steps: T.
    dt: step, s.

  Returns:
    trajectories: (B, N, T, 2) float32 positions [x, y] in metres after each step.
    num_modes: (B,) int true number of modes.
    mode_ids: (B, N) int mode index (0..num_modes-1) of each sample.
  """
  rng = np.random.default_rng(seed)
  if num_modes is None:
    num_modes = rng.integers(1, 4, size=num_sets)
  num_modes = np.broadcast_to(np.asarray(num_modes, int), (num_sets,))
  if np.any(num_modes < 1) or np.any(num_modes > 3) or 2 * num_modes.max() > num_samples:
    raise ValueError(f"mode_sets: num_modes must be in 1..3 with 2 samples each, got "
                     f"{np.unique(num_modes)} for num_samples={num_samples}")
  t = dt * np.arange(1, num_steps + 1)
  trajectories = np.empty((num_sets, num_samples, num_steps, 2))
  mode_ids = np.empty((num_sets, num_samples), int)
  for b, k in enumerate(num_modes):
    kinds = rng.choice(len(MODE_KINDS), size=k, replace=False)
    extra = rng.multinomial(num_samples - 2 * k, np.full(k, 1.0 / k))
    ids = np.repeat(np.arange(k), 2 + extra)
    lanes, brakes = np.array([MODE_KINDS[i] for i in kinds]).T
    start = rng.uniform(0.3, 1.5, k)[ids] + rng.normal(0, 0.15, num_samples)
    duration = rng.uniform(3.0, 4.5, k)[ids] + rng.normal(0, 0.15, num_samples)
    u = np.clip((t[None] - start[:, None]) / duration[:, None], 0.0, 1.0)
    smooth = u ** 3 * (10 - 15 * u + 6 * u ** 2)
    speed = rng.uniform(22, 38) + rng.normal(0, 0.5, num_samples)
    accel = brake * brakes[ids] + rng.normal(0, 0.15, num_samples)
    x = speed[:, None] * t + 0.5 * accel[:, None] * t ** 2
    y = LANE_WIDTH * lanes[ids][:, None] * smooth + rng.normal(0, 0.15, (num_samples, 1))
    noise = rng.normal(0, 0.03, (num_samples, num_steps, 2))
    trajectories[b] = np.stack([x, y], axis=-1) + noise
    mode_ids[b] = ids
  return trajectories.astype(np.float32), num_modes.copy(), mode_ids
