"""evaluation/prediction_cache.py: the cache returns what the predictor said."""

import types

import ml_collections
import numpy as np

from cvmdx_jax.config.sampling import SamplingConfig
from cvmdx_jax.evaluation import prediction_cache


def _fake_predictor(calls):
  def predict(scenarios, seed=0):
    calls.append(seed)
    m = len(scenarios.xi)
    rng = np.random.default_rng(seed)
    traj = rng.normal(size=(m, 4, 125, 2)).astype(np.float32)
    probs = np.tile(np.array([0.75, 0.25, 0.0], np.float32), (m, 1))
    hyp = types.SimpleNamespace(means=traj[:, :3], probs=probs, labels=np.zeros((m, 4), np.int32))
    return types.SimpleNamespace(
        prediction=types.SimpleNamespace(trajectories=traj),
        hypotheses=hyp,
        q=np.arange(m),
        delta=np.array([1.0, 5.0, np.nan][:m], np.float32),
    )

  predict.delta_limit = 2.0
  return predict


def test_cache_predicts_once_per_inputs_and_seed(tmp_path):
  calls = []
  fake = _fake_predictor(calls)
  cached = prediction_cache.cached(fake, tmp_path / "predictions", "run", "model-a")
  xi = np.random.default_rng(0).normal(size=(3, 9, 75, 4)).astype(np.float32)
  scen = types.SimpleNamespace(xi=xi, mask=np.ones(xi.shape[:3], bool))
  first = cached(scen, 0)
  again = cached(scen, 0)
  assert calls == [0]  # the second call read the cache
  want = fake(scen, seed=0)
  for out in (first, again):
    np.testing.assert_array_equal(out.prediction.trajectories, want.prediction.trajectories)
    np.testing.assert_array_equal(out.prediction.mean, want.prediction.trajectories.mean(1))
    np.testing.assert_array_equal(out.hypotheses.probs, want.hypotheses.probs)
    np.testing.assert_array_equal(out.hypotheses.num_modes, [2, 2, 2])
    np.testing.assert_array_equal(out.q, want.q)
    np.testing.assert_array_equal(out.out_of_distribution, [False, True, True])  # NaN: out
  cached(scen, 1)
  other = types.SimpleNamespace(xi=xi + 1.0, mask=scen.mask)
  cached(other, 0)
  assert calls == [0, 0, 1, 0]  # `want` above, then a new seed and new inputs predict
  prediction_cache.cached(fake, tmp_path / "predictions", "run", "model-b")(scen, 0)
  assert calls == [0, 0, 1, 0, 0]  # another model (retrained, other sampling) predicts
  assert len(list((tmp_path / "predictions").glob("run_*.npz"))) == 4


def test_model_id_follows_checkpoints_and_sampling():
  def predictor(params_id="t1", weight=1.0, steps=2):
    return types.SimpleNamespace(
        tokenizer=types.SimpleNamespace(
            checkpoint=ml_collections.FrozenConfigDict({"params_id": params_id, "step": 5})
        ),
        denoiser=types.SimpleNamespace(params={"w": np.full((2, 3), weight, np.float32)}),
        sampling=SamplingConfig(steps=steps),
    )

  base = prediction_cache.model_id(predictor())
  assert prediction_cache.model_id(predictor()) == base
  for changed in (predictor(params_id="t2"), predictor(weight=1.5), predictor(steps=3)):
    assert prediction_cache.model_id(changed) != base
