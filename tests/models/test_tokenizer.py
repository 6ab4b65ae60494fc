"""Tokeniser model: normalisation, masked/weighted loss, maneuver classifier learning."""

import jax
import jax.numpy as jnp
import numpy as np

from configs import tokenizer as tokenizer_config
from cvmdx_jax.config.runs import TokenizerRunConfig
from cvmdx_jax.models import scenario_norm
from cvmdx_jax.models import tokenizer as tok
from cvmdx_jax.train import tokenizer as train_tok


def test_normalisation_hand_values_and_mask():
  xi = np.array([[[[50.0, -3.5, 35.0, 0.25]], [[1.0, 2.0, 3.0, 4.0]]]], np.float32)  # (1,2,1,4)
  mask = np.array([[[True], [False]]])
  out = np.asarray(scenario_norm.encoder_input(xi, mask))
  np.testing.assert_allclose(out[0, 0, 0], [0.5, -1.0, 2.5, 2.5, 1.0], rtol=1e-6)
  np.testing.assert_array_equal(out[0, 1, 0], [0, 0, 0, 0, 0])
  np.testing.assert_allclose(scenario_norm.denormalize_xi(out[0, 0, 0, :4]), xi[0, 0, 0], rtol=1e-6)


_loss = jax.jit(lambda model, batch, cfg: tok.loss_fn(*model, batch, cfg), static_argnums=2)


def _model(seed=0):
  cfg = TokenizerRunConfig.from_config(tokenizer_config.get_config("tiny")).model
  graphdef, params = tok.init_tokenizer(cfg, jax.random.key(seed))
  return cfg, (graphdef, params)


def test_loss_ignores_padding_rows_and_absent_vehicles(scenarios_factory):
  cfg, model = _model()
  s = scenarios_factory(6)
  batch = {
      "xi": jnp.asarray(s.xi),
      "mask": jnp.asarray(s.mask),
      "label": jnp.asarray(s.label),
      "weight": jnp.ones(6),
  }
  loss, _ = _loss(model, batch, cfg)
  garbage = scenarios_factory(3, seed=9)
  padded = {
      "xi": jnp.concatenate([batch["xi"], 1e3 * jnp.asarray(garbage.xi)]),
      "mask": jnp.concatenate([batch["mask"], jnp.asarray(garbage.mask)]),
      "label": jnp.concatenate([batch["label"], jnp.asarray(garbage.label)]),
      "weight": jnp.concatenate([jnp.ones(6), jnp.zeros(3)]),
  }
  np.testing.assert_allclose(_loss(model, padded, cfg)[0], loss, rtol=1e-5)
  # values under a False mask do not matter
  hidden = {**batch, "xi": jnp.where(batch["mask"][..., None], batch["xi"], 77.0)}
  np.testing.assert_allclose(_loss(model, hidden, cfg)[0], loss, rtol=1e-5)


def test_total_loss_is_the_weighted_sum_of_its_terms(scenarios_factory):
  cfg, model = _model(1)
  s = scenarios_factory(5)
  batch = {"xi": s.xi, "mask": s.mask, "label": s.label, "weight": np.ones(5, np.float32)}
  loss, (m, out) = _loss(model, batch, cfg)
  expected = (
      m["reconstruction"]
      + m["codebook"]
      + cfg.quantizer.beta * m["commitment"]
      + cfg.cls_weight * m["classification"]
  )
  np.testing.assert_allclose(loss, expected, rtol=1e-6)
  logits = np.asarray(out.logits, np.float64)
  ce = -(logits[np.arange(5), s.label] - np.log(np.exp(logits).sum(-1))).mean()
  np.testing.assert_allclose(m["classification"], ce, rtol=1e-5)


def test_reconstruction_weighs_the_ego_by_ego_weight(scenarios_factory):
  cfg, model = _model(2)
  assert cfg.ego_weight != 1.0
  s = scenarios_factory(4)
  batch = {"xi": s.xi, "mask": s.mask, "label": s.label, "weight": np.ones(4, np.float32)}
  _, (m, out) = _loss(model, batch, cfg)
  target = np.asarray(scenario_norm.normalize_xi(s.xi, s.mask), np.float64)
  sq = (np.asarray(out.reconstruction, np.float64) - target) ** 2  # (4, 9, 75, 4)
  w = np.where(s.mask, 1.0, 0.0)[..., None] * np.ones(4)
  w[:, 0] *= cfg.ego_weight
  expected = np.mean([(w[b] * sq[b]).sum() / w[b].sum() for b in range(4)])
  np.testing.assert_allclose(m["reconstruction"], expected, rtol=1e-5)


def test_classifier_beats_chance_on_separable_toy_set(scenarios_factory):
  config = tokenizer_config.get_config("tiny")
  config.quantizer.codebook_size = 16
  run = TokenizerRunConfig.from_config(config)
  cfg, tx = run.model, train_tok.optimizer(run.train)
  graphdef = tok.make_graphdef(cfg)
  state = train_tok.make_init_fn(cfg, tx)(jax.random.key(0))
  step = jax.jit(train_tok.make_step_fn(graphdef, cfg, tx))
  s = scenarios_factory(96)
  for i in range(120):
    rows = np.random.default_rng(i).choice(96, 16, replace=False)
    batch = {
        "xi": s.xi[rows],
        "mask": s.mask[rows],
        "label": s.label[rows],
        "weight": np.ones(16, np.float32),
    }
    state, _ = step(state, batch, jax.random.key(i))
  test = scenarios_factory(60, seed=5)
  _, _, logits = train_tok.encode(graphdef, state["params"], test.xi, test.mask, 32)
  accuracy = float(np.mean(np.argmax(logits, -1) == test.label))
  assert accuracy > 0.6, accuracy  # chance is 1/3
