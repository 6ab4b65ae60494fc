"""The temperature of p(c) chosen on val (temperature scaling, Guo et al. 2017).

A hypothesis's share of samples says how often the model samples its mode, not how often
its mean is the hypothesis closest to the truth at 5 s (the one minFDE_K, Brier-minFDE and
the reliability diagram judge). `multimodal.hypotheses.temper` maps shares to p(c) =
share^t / sum share^t; on val scenarios the t of a grid with the lowest mean log loss of
the closest hypothesis is chosen (`log_losses`, `choose`: the event's own proper score, one
parameter fitted), and `with_temperature` gives a `Predictor` that predicts with it.
"""

import dataclasses

import numpy as np

from cvmdx_jax.evaluation import metrics
from cvmdx_jax.multimodal import hypotheses

TEMPERATURES = (0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0)  # the grid (1: the paper's share)
_FLOOR = 1e-6  # probability floor of the log loss (a closest hypothesis given p = 0)


def closest_hypothesis(means, probs, gt) -> np.ndarray:
  """Index (M,) of the non-empty hypothesis (probs > 0) closest to gt at the last step:
  means (M, K, T, 2), probs (M, K), gt (M, T, 2) in metres."""
  return np.asarray(metrics.closest_final(means, gt, probs > 0))


def closest_log_loss(probs, closest) -> np.ndarray:
  """-log p of the closest hypothesis (nats, floored at p = 1e-6) per scenario: probs (M,
  K), closest (M,) int -> (M,)."""
  p = np.asarray(probs, np.float64)[np.arange(len(closest)), np.asarray(closest)]
  return -np.log(np.maximum(p, _FLOOR))


def log_losses(shares, closest, temperatures=TEMPERATURES) -> np.ndarray:
  """Mean -log p(closest) (nats) over scenarios for each temperature: shares (M, K) the
  untempered p(c) (temperature 1), closest (M,) int -> (len(temperatures),)."""
  return np.asarray(
      [
          float(np.mean(closest_log_loss(hypotheses.temper(shares, float(t)), closest)))
          for t in temperatures
      ]
  )


def choose(losses, temperatures=TEMPERATURES) -> float:
  """The temperature of the lowest of `losses` (`log_losses`); ties take the one nearest 1."""
  losses = np.asarray(losses, np.float64)
  order = np.argsort(np.abs(np.asarray(temperatures) - 1.0), kind="stable")
  return float(temperatures[order[np.argmin(losses[order])]])


def with_temperature(predictor, temperature: float):
  """`predictor` (an `inference.predictor.Predictor`) predicting p(c) with `temperature`."""
  sampling = predictor.sampling
  hyp = dataclasses.replace(sampling.hypotheses, prob_temperature=float(temperature))
  return dataclasses.replace(predictor, sampling=dataclasses.replace(sampling, hypotheses=hyp))
