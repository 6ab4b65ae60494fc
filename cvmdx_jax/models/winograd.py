"""Width-3, stride-1, zero-padded ("SAME") 1-D convolution by Winograd's minimal
filtering F(4, 3) (Lavin & Gray 2016, "Fast Algorithms for Convolutional Neural Networks").

Per tile of 4 outputs, the 6 inputs d and the 3 taps g are transformed (U = B^T d, V = G g),
multiplied per transformed position (6 GEMMs over channels instead of 12 for the direct
convolution) and transformed back (y = A^T (U V)). The same convolution up to float32
rounding (~5e-6 relative); its gradients come from autodiff through the same GEMMs, so the
forward and both backward convolutions do half the multiplies. On XLA:CPU 0.10 (2-core
AVX-512, batch 256) forward + backward is 1.3-1.7x faster than `lax.conv_general_dilated`
where both channel counts are >= 128, and not faster below (docs/log, "Winograd").

`conv3` takes it as the performance option `winograd` says (`models.performance`):
"auto" (default) on the CPU backend only, chosen per platform when the function is
lowered (elsewhere XLA's convolution, `direct_conv`); "on" wherever the channels allow,
"off" never. Set by `CVMDX_WINOGRAD=auto|on|off` or `performance.use`.

For inference the kernels' transform V = G g can be done once (`prepare_kernel`,
`unet1d.prepare_params`, which `Predictor` calls): `conv3` applies a transformed kernel
(6 rows instead of 3 taps) by F(4, 3) directly, whatever the option and the length.
"""

import jax
import jax.numpy as jnp

from cvmdx_jax.models import performance

TILE = 4  # outputs per tile
MIN_CHANNELS = 128  # `conv3` uses F(4, 3) where both channel counts reach this
# B^T (6 x 6), G (6 x 3), A^T (4 x 6) of F(4, 3) for correlation y_i = sum_k d_{i+k} g_k
_BT = (
    (4, 0, -5, 0, 1, 0),
    (0, -4, -4, 1, 1, 0),
    (0, 4, -4, -1, 1, 0),
    (0, -2, -1, 2, 1, 0),
    (0, 2, -1, -2, 1, 0),
    (0, 4, 0, -5, 0, 1),
)
_G = (
    (1 / 4, 0, 0),
    (-1 / 6, -1 / 6, -1 / 6),
    (-1 / 6, 1 / 6, -1 / 6),
    (1 / 24, 1 / 12, 1 / 6),
    (1 / 24, -1 / 12, 1 / 6),
    (0, 0, 1),
)
_AT = ((1, 1, 1, 1, 1, 0), (0, 1, -1, 2, -2, 0), (0, 1, 1, 4, 4, 0), (0, 1, -1, 8, -8, 1))


def _combine(matrix, terms):
  """matrix (R, N) applied to a list of N equal-shape arrays, as explicit sums that XLA
  fuses into one elementwise pass (zero coefficients skipped) -> list of R arrays."""
  rows = []
  for row in matrix:
    parts = [t if c == 1 else -t if c == -1 else c * t for c, t in zip(row, terms) if c != 0]
    rows.append(sum(parts[1:], parts[0]))
  return rows


def transform_kernel(kernel):
  """The taps (3, C, O) in the transformed domain of F(4, 3): V = G g, (6, C, O)."""
  return jnp.stack(_combine(_G, list(kernel)))


def winograd_conv(x, kernel):
  """x (B, L, C), kernel (3, C, O) or its `transform_kernel` (6, C, O) -> (B, L, O):
  output i is sum_k x[i + k - 1] @ kernel[k], x zero outside [0, L). A length that is not
  a multiple of 4 is zero-padded on the right and cropped back (the same zeros as "SAME")."""
  b, length, channels = x.shape
  tiles = -(-length // TILE)
  # blocks of 4: tile t reads padded positions 4 t .. 4 t + 5 (block t and two of t + 1)
  right = tiles * TILE - length + TILE - 1
  blocks = jnp.pad(x, ((0, 0), (1, right), (0, 0))).reshape(b, tiles + 1, TILE, channels)
  inputs = [blocks[:, :tiles, p] if p < TILE else blocks[:, 1:, p - TILE] for p in range(TILE + 2)]
  u = jnp.stack(_combine(_BT, inputs)).reshape(TILE + 2, b * tiles, channels)
  v = kernel if is_transformed(kernel) else transform_kernel(kernel)  # (6, C, O)
  m = jax.lax.dot_general(u, v, (((2,), (1,)), ((0,), (0,))))  # (6, B tiles, O)
  y = jnp.stack(_combine(_AT, list(m)), axis=1)  # (B tiles, 4, O)
  return y.reshape(b, tiles * TILE, -1)[:, :length]


def is_transformed(kernel) -> bool:
  """Whether `kernel` is a `transform_kernel` output (6 rows) rather than 3 taps."""
  return kernel.shape[0] == TILE + 2


def prepare_kernel(kernel):
  """`kernel` (3, C, O) for inference: transformed once (`transform_kernel`) where `conv3`
  takes F(4, 3) for it on this backend, so that no call repeats the transform; else as is
  (also a kernel transformed already)."""
  if is_transformed(kernel) or not eligible(kernel):
    return kernel
  fast = performance.current().resolved(jax.default_backend())["winograd"]
  return transform_kernel(kernel) if fast else kernel


def eligible(kernel) -> bool:
  """Whether both channel counts of `kernel` (K, C, O) reach MIN_CHANNELS."""
  return min(kernel.shape[1:]) >= MIN_CHANNELS


def direct_conv(x, kernel):
  """XLA's convolution, the same function as `winograd_conv` for any length."""
  return jax.lax.conv_general_dilated(
      x, kernel, (1,), ((1, 1),), dimension_numbers=("NWC", "WIO", "NWC")
  )


def conv3(x, kernel):
  """The width-3 "SAME" convolution x (B, L, C) * kernel (3, C, O) -> (B, L, O):
  `winograd_conv` where C, O >= MIN_CHANNELS, L % 4 == 0 and the `winograd` performance
  option takes it (module docstring), else XLA's convolution; a `prepare_kernel`ed
  (transformed) kernel always by `winograd_conv`, at any L."""
  if is_transformed(kernel):
    return winograd_conv(x, kernel)
  _, length, channels = x.shape
  if eligible(kernel) and length % TILE == 0:
    return performance.select("winograd", winograd_conv, direct_conv, x, kernel)
  return direct_conv(x, kernel)
