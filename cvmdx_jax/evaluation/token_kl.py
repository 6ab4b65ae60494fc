"""KL between the data and the model distributions of the 5 s position, per codebook entry
(paper Fig. 3: how the model fits rare and frequent tokens)."""

import dataclasses

import numpy as np


def gaussian_kl(mu_p, cov_p, mu_q, cov_q) -> float:
  """KL(N(mu_p, cov_p) || N(mu_q, cov_q)) in nats (closed form)."""
  d = len(mu_p)
  inv_q = np.linalg.inv(cov_q)
  diff = mu_q - mu_p
  return 0.5 * float(
      np.trace(inv_q @ cov_p)
      + diff @ inv_q @ diff
      - d
      + np.linalg.slogdet(cov_q)[1]
      - np.linalg.slogdet(cov_p)[1]
  )


@dataclasses.dataclass(frozen=True)
class TokenKL:
  """Per codebook entry: training usage N_q and KL(p_q(Y) || p_theta,q(Y))."""

  token: np.ndarray
  usage: np.ndarray
  kl: np.ndarray


def kl_per_token(
    q_test, future, samples, train_usage, min_members: int = 3, ridge: float = 0.25
) -> TokenKL:
  """KL between the data and model distributions of the 5 s position per token.

  p_q: Gaussian of the ground-truth final positions of the test scenarios with token
  q; p_theta,q: Gaussian of all model samples' final positions for those scenarios.
  A ridge (m^2) keeps tiny clusters' covariances invertible.

  Args:
    q_test: (M,) test tokens; future: (M, T, 2); samples: (M, N, T, 2);
    train_usage: (Q,) training scenarios per token (N_q).
  """
  rows = []
  for token in np.unique(q_test):
    sel = q_test == token
    if sel.sum() < min_members or train_usage[token] == 0:
      continue
    data = np.asarray(future)[sel, -1]
    model = np.asarray(samples)[sel, :, -1].reshape(-1, 2)
    eye = ridge * np.eye(2)
    rows.append(
        (
            token,
            train_usage[token],
            gaussian_kl(data.mean(0), np.cov(data.T) + eye, model.mean(0), np.cov(model.T) + eye),
        )
    )
  arr = np.array(rows, np.float64).reshape(-1, 3)
  return TokenKL(token=arr[:, 0].astype(int), usage=arr[:, 1], kl=arr[:, 2])
