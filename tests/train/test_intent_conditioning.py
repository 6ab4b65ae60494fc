"""The intent-conditioned denoiser (`diffusion.intent_conditioning`): its classifier, its
cross-entropy in the train step, the per-sample classes in sampling, configs, students."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from configs import diffusion as diffusion_config
from configs import distill as distill_config
from cvmdx_jax import ego_motion
from cvmdx_jax.config.fields import ConfigFieldError
from cvmdx_jax.config.runs import DiffusionRunConfig, DistillRunConfig
from cvmdx_jax.config.sampling import SamplingConfig, check_sampling
from cvmdx_jax.diffusion import cosine_schedule
from cvmdx_jax.inference import sampling
from cvmdx_jax.models import unet1d
from cvmdx_jax.runs import fingerprints
from cvmdx_jax.train import diffusion as diffusion_train
from cvmdx_jax.train import distill
from tests.inference.denoisers import bundle
from tests.models import tiny_nets

EGO = tiny_nets.unet_config(5, cond_dim=10, cond_hidden=(24, 12))
INTENT = dataclasses.replace(EGO, num_intents=3, intent_features=7)
# the same U-Net reading the real ego features (ego_motion.NUM_FEATURES), as a run's does
FEATURES = ego_motion.NUM_FEATURES
RUN_INTENT = dataclasses.replace(INTENT, cond_dim=FEATURES + 3, intent_features=FEATURES)
META = {"checkpoint": {"fingerprint": {}, "step": 1, "params_id": "x"}}


def _demo(**diffusion):
  config = diffusion_config.get_config("demo")
  for field, value in diffusion.items():
    config.diffusion[field] = value
  return DiffusionRunConfig.from_config(config).with_tokens(8)


def test_the_classifier_is_an_mlp_on_the_ego_features_and_adds_only_itself():
  g, p = unet1d.init_unet(INTENT, jax.random.key(0))
  _, plain = unet1d.init_unet(EGO, jax.random.key(0))
  assert [p["intent_mlp"][i]["kernel"].shape for i in range(3)] == [(7, 24), (24, 12), (12, 3)]
  # every other parameter draws as without it: earlier runs keep their init
  assert jax.tree.all(
      jax.tree.map(np.array_equal, {k: v for k, v in p.items() if k != "intent_mlp"}, plain)
  )
  f = jax.random.normal(jax.random.key(1), (4, 7))
  layer = lambda h, w: h @ w["kernel"] + w["bias"]
  h = jax.nn.silu(layer(jax.nn.silu(layer(f, p["intent_mlp"][0])), p["intent_mlp"][1]))
  np.testing.assert_allclose(
      unet1d.apply_intent(g, p, f), layer(h, p["intent_mlp"][2]), rtol=1e-5, atol=1e-6
  )
  for bad in (
      dict(num_intents=3),
      dict(intent_features=7),
      dict(num_intents=3, intent_features=11),
  ):
    with pytest.raises(ValueError, match="intent_features"):
      dataclasses.replace(EGO, **bad)


def test_intent_cross_entropy_is_the_weighted_mean_negative_log_likelihood():
  logits = jnp.array([[2.0, 0.0, -1.0], [0.0, 0.0, 0.0], [1.0, 3.0, 0.5]])
  label = jnp.array([0, 2, 1])
  weight = jnp.array([2.0, 1.0, 0.0])  # the last row is padding
  p0 = np.exp(2.0) / (np.exp(2.0) + 1.0 + np.exp(-1.0))
  want = (2.0 * -np.log(p0) + 1.0 * np.log(3.0)) / 3.0
  np.testing.assert_allclose(
      diffusion_train.intent_cross_entropy(logits, label, weight), want, rtol=1e-6
  )


def test_the_train_step_adds_the_cross_entropy_and_trains_the_classifier():
  b, key = 6, jax.random.key(3)
  label = jnp.arange(b) % 3
  ego = jnp.concatenate(
      [jax.random.normal(jax.random.key(2), (b, 7)), jax.nn.one_hot(label, 3)], -1
  )
  batch = {
      "x0": 0.3 * jax.random.normal(jax.random.key(1), (b, 125, 2)),
      "q": jnp.arange(b) % 5,
      "ego": ego,
      "weight": jnp.array([1.0] * (b - 1) + [0.0]),
      "label": label,
  }
  tx = diffusion_train.optimizer(DiffusionRunConfig().train, 10)
  steps = {}
  for name, cfg in (("plain", EGO), ("intent", INTENT)):
    g = unet1d.make_graphdef(cfg)
    state = diffusion_train.make_init_fn(cfg, tx)(jax.random.key(0))
    step = diffusion_train.make_step_fn(
        g, cfg, tx, cond_drop_prob=0.1, ema_decay=0.9, num_steps=1000
    )
    steps[name] = (g, state) + step(state, batch, key)
  g, state, new, metrics = steps["intent"]
  plain_metrics = steps["plain"][3]
  assert set(metrics) == {"loss", "grad_norm", "intent_ce"} and "intent_ce" not in plain_metrics
  # same U-Net parameters, same key: the v-loss is the same, the cross-entropy adds to it
  np.testing.assert_allclose(
      metrics["loss"], plain_metrics["loss"] + metrics["intent_ce"], rtol=1e-5
  )
  logits = unet1d.apply_intent(g, state["params"], ego[:, :7])
  np.testing.assert_allclose(
      metrics["intent_ce"],
      diffusion_train.intent_cross_entropy(logits, label, batch["weight"]),
      rtol=1e-5,
  )
  assert not np.array_equal(
      new["params"]["intent_mlp"][2]["kernel"], state["params"]["intent_mlp"][2]["kernel"]
  )


@pytest.mark.parametrize("probs", [(0.5, 0.25, 0.25), (0.1, 0.0, 0.9), (0.34, 0.33, 0.33)])
def test_draw_intents_gives_each_class_its_share_of_the_samples_up_to_one(probs):
  n = 16
  logits = jnp.log(jnp.asarray(probs) + 1e-30)
  for seed in range(20):
    classes = np.asarray(sampling.draw_intents(logits, jax.random.key(seed), n))
    counts = np.bincount(classes, minlength=3)
    assert counts.sum() == n and np.all(np.abs(counts - n * np.asarray(probs)) < 1.0 + 1e-6)
    assert np.all(np.diff(classes) >= 0)  # in class order
  # the shares hold in expectation (the one uniform offset is drawn afresh per key)
  mean = (
      np.mean(
          [
              np.bincount(
                  np.asarray(sampling.draw_intents(logits, jax.random.key(s), 3)), minlength=3
              )
              for s in range(2000)
          ],
          axis=0,
      )
      / 3
  )
  np.testing.assert_allclose(mean, probs, atol=0.03)


def test_sample_rows_of_features_each_condition_their_own_sample():
  """ego (N, F): sample i sees row i in both guidance branches; equal rows are (F,)."""
  g, p = unet1d.init_unet(EGO, jax.random.key(0))
  p = jax.tree.map(lambda a: a + 0.05 * jax.random.normal(jax.random.key(9), a.shape), p)
  config = dataclasses.replace(SamplingConfig(), num_samples=4, steps=2)
  run = lambda ego: sampling.sample_controls(
      g,
      p,
      1,
      0.5,
      jax.random.key(3),
      schedule=cosine_schedule(1000),
      null_token=5,
      config=config,
      ego=ego,
  )
  row = jax.random.normal(jax.random.key(4), (10,))
  rows = jnp.tile(row, (4, 1))
  np.testing.assert_array_equal(run(rows), run(row))
  other = run(rows.at[2].set(-row))
  base = run(rows)
  np.testing.assert_allclose(np.delete(other, 2, 0), np.delete(base, 2, 0), atol=1e-6)
  assert not np.allclose(other[2], base[2], atol=1e-3)


@pytest.mark.usefixtures("float32_arithmetic")  # batched vs one by one: other TF32 kernels on a GPU
def test_predict_batch_conditions_each_sample_on_a_class_drawn_from_the_classifier():
  g, p = unet1d.init_unet(RUN_INTENT, jax.random.key(0))
  p = jax.tree.map(lambda a: a + 0.05 * jax.random.normal(jax.random.key(9), a.shape), p)
  config = dataclasses.replace(SamplingConfig(), num_samples=4, steps=2)
  denoiser = _demo(intent_conditioning=True).diffusion
  b = 2
  ego = jax.random.normal(jax.random.key(4), (b, FEATURES))
  keys = jax.random.split(jax.random.key(5), b)
  kw = dict(schedule=cosine_schedule(1000), config=config)
  # a classifier sure of class 2: every sample of both scenarios sees the one-hot of 2
  bias = p["intent_mlp"][2]["bias"]
  sure = jax.tree.map(lambda a: a, p)
  sure["intent_mlp"][2]["bias"] = bias.at[2].set(1e4)
  residual = dataclasses.replace(denoiser, conditioning="ego_film")
  got = sampling.predict_batch(
      bundle(g, sure, RUN_INTENT, residual),
      jnp.array([1, 2]),
      jnp.zeros(b),
      jnp.full(b, 30.0),
      jnp.zeros(b),
      keys,
      ego,
      **kw,
  )
  sample_keys = jax.vmap(jax.random.split)(keys)[:, 0]
  for i in range(b):
    want = sampling.sample_controls(
        g,
        sure,
        jnp.array([1, 2])[i],
        0.0,
        sample_keys[i],
        ego=jnp.concatenate([ego[i], jnp.eye(3)[2]]),
        null_token=5,
        **kw,
    )
    np.testing.assert_allclose(
        got.controls[i] / jnp.asarray(residual.control_scale), want, atol=1e-5
    )


@pytest.mark.usefixtures("float32_arithmetic")  # batched vs one by one: other TF32 kernels on a GPU
def test_the_intent_prior_reweights_the_class_draws():
  g, p = unet1d.init_unet(RUN_INTENT, jax.random.key(0))
  p = jax.tree.map(lambda a: a + 0.05 * jax.random.normal(jax.random.key(9), a.shape), p)
  # a classifier with equal logits for every input: p = (1/3, 1/3, 1/3)
  p["intent_mlp"][2] = jax.tree.map(jnp.zeros_like, p["intent_mlp"][2])
  # keep-lane weight 2: (2, 1, 1) / 4, so 4 systematic draws are exactly kl, kl, lcr, lcl
  config = SamplingConfig(num_samples=4, steps=2, intent_prior=(2, 1, 1))
  denoiser = dataclasses.replace(_demo(intent_conditioning=True).diffusion, conditioning="ego_film")
  ego = jax.random.normal(jax.random.key(4), (1, FEATURES))
  keys = jax.random.split(jax.random.key(5), 1)
  kw = dict(schedule=cosine_schedule(1000), config=config)
  got = sampling.predict_batch(
      bundle(g, p, RUN_INTENT, denoiser),
      jnp.array([1]),
      jnp.zeros(1),
      jnp.full(1, 30.0),
      jnp.zeros(1),
      keys,
      ego,
      **kw,
  )
  rows = jnp.concatenate([jnp.tile(ego, (4, 1)), jnp.eye(3)[jnp.array([0, 0, 1, 2])]], -1)
  want = sampling.sample_controls(
      g, p, jnp.array(1), 0.0, jax.random.split(keys[0])[0], ego=rows, null_token=5, **kw
  )
  np.testing.assert_allclose(got.controls[0] / jnp.asarray(denoiser.control_scale), want, atol=1e-5)
  without = dataclasses.replace(denoiser, intent_conditioning=False)
  with pytest.raises(ConfigFieldError, match="no maneuver classes"):
    check_sampling(config, without)  # what predict_batch checks first
  with pytest.raises(ConfigFieldError, match="3 weights") as error:
    SamplingConfig(intent_prior=(2, 1))
  assert error.value.field == "intent_prior"
  with pytest.raises(ConfigFieldError):
    SamplingConfig(intent_prior=(0, 1, 1))


def test_configs_check_and_fingerprint_the_intent_conditioning():
  off, on = _demo(intent_conditioning=False), _demo(intent_conditioning=True)
  assert (on.model.num_intents, on.model.intent_features) == (3, 41)
  assert on.model.cond_dim == off.model.cond_dim + 3
  off_print = fingerprints.diffusion(off, "data", META)
  assert off_print["model"]["num_intents"] == 0 and off_print["intent_conditioning"] is False
  on_print = fingerprints.diffusion(on, "data", META)
  assert on_print["model"]["num_intents"] == 3 and on_print["intent_conditioning"] is True
  with pytest.raises(ConfigFieldError, match="ego_film") as error:
    _demo(intent_conditioning=True, conditioning="token")
  assert error.value.field == "diffusion.intent_conditioning"
  with pytest.raises(ValueError, match="num_intents"):
    dataclasses.replace(on, model=dataclasses.replace(on.model, num_intents=0, intent_features=0))


def test_the_student_keeps_the_teachers_classifier():
  teacher = _demo(intent_conditioning=True)
  student = distill.student_config(
      teacher, DistillRunConfig.from_config(distill_config.get_config("tiny"))
  )
  assert student.model.num_intents == 3 and student.model.cond_dim == teacher.model.cond_dim + 1
  small = dict(base_channels=16, channel_mult=(1, 2), attention_levels=(1,), groups=8)
  _, teacher_params = unet1d.init_unet(
      dataclasses.replace(teacher.model, **small), jax.random.key(0)
  )
  _, fresh = unet1d.init_unet(dataclasses.replace(student.model, **small), jax.random.key(1))
  got = distill.student_params(teacher_params, fresh)
  assert jax.tree.all(jax.tree.map(np.array_equal, got["intent_mlp"], teacher_params["intent_mlp"]))
