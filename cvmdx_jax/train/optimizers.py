"""The AdamW schedule the denoiser and the learned baselines train with."""

import optax


def adamw(t, total_steps: int, end_value: float) -> optax.GradientTransformation:
  """AdamW of a `train` section `t`: linear warm-up from 1 % of the peak `t.learning_rate`
  over min(`t.warmup_steps`, 10 % of the run), cosine decay to `end_value` at `total_steps`,
  global-norm clipping at `t.grad_clip`, decoupled weight decay `t.weight_decay`."""
  warmup = min(t.warmup_steps, max(total_steps // 10, 1))
  lr = optax.warmup_cosine_decay_schedule(
      init_value=t.learning_rate * 0.01,
      peak_value=t.learning_rate,
      warmup_steps=warmup,
      decay_steps=max(total_steps, warmup + 1),
      end_value=end_value,
  )
  return optax.chain(
      optax.clip_by_global_norm(t.grad_clip), optax.adamw(lr, weight_decay=t.weight_decay)
  )
