"""The scene, moving: a GIF of a window of a recording with each vehicle's predicted
hypotheses (matplotlib's PillowWriter).

Drawn in the recording's image frame (highD's x right, y down, so it overlays the
background image): lane markings of the recording meta (outer ones solid, the others
dashed), every vehicle present as a box (length x width at its centre), and for each
vehicle predicted at that frame its hypothesis means, line width and opacity growing with
the probability, the probability written at the end of each line.
"""

import dataclasses
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after the backend)
import numpy as np  # noqa: E402
from matplotlib import animation as mpl_animation  # noqa: E402
from matplotlib import patches  # noqa: E402

from cvmdx_jax import constants  # noqa: E402
from cvmdx_jax.data import frames as frames_lib  # noqa: E402
from cvmdx_jax.data import highd  # noqa: E402
from cvmdx_jax.inference import recording  # noqa: E402
from cvmdx_jax.storage import atomic  # noqa: E402

_DEFAULT_SIZE = (4.5, 1.9)  # m, a car, where the tracksMeta size is unknown
_COLOURS = plt.get_cmap("tab10").colors


def _draw_road(ax, scene: dict, x_range) -> None:
  for markings in (scene["upper"], scene["lower"]):
    for k, y in enumerate(markings):
      outer = k in (0, len(markings) - 1)
      ax.plot(
          x_range, [y, y], color="0.3", lw=1.2 if outer else 0.8, ls="-" if outer else (0, (6, 6))
      )


def _draw_frame(ax, rec, scene: dict, frame: int, preds, x_range, y_range) -> None:
  ax.clear()
  ax.set_facecolor("0.92")
  _draw_road(ax, scene, x_range)
  rows = np.flatnonzero(rec.frame == frame)
  centres = frames_lib.image_centre(rec, rows)
  for row, (cx, cy) in zip(rows, centres):
    track = int(rec.track_id[row])
    length, width = scene["length"][track], scene["width"][track]
    if not (np.isfinite(length) and np.isfinite(width)):
      length, width = _DEFAULT_SIZE
    colour = _COLOURS[track % len(_COLOURS)]
    ax.add_patch(
        patches.Rectangle(
            (cx - length / 2, cy - width / 2),
            length,
            width,
            facecolor=colour,
            edgecolor="k",
            lw=0.5,
        )
    )
  if preds is not None:
    for i in np.flatnonzero(preds.frame == frame):
      colour = _COLOURS[int(preds.track_id[i]) % len(_COLOURS)]
      for c in np.flatnonzero(preds.probs[i] > 0):
        p, path = preds.probs[i, c], preds.means[i, c]
        ax.plot(path[:, 0], path[:, 1], color=colour, lw=0.6 + 2.0 * p, alpha=0.35 + 0.65 * p)
        ax.text(path[-1, 0], path[-1, 1], f"{p:.2f}", fontsize=5, color=colour, clip_on=True)
  ax.set_xlim(*x_range)
  ax.set_ylim(y_range[1], y_range[0])  # y down, as the image
  ax.set_aspect("equal")
  ax.set_title(
      f"recording {rec.recording_id}, frame {frame} "
      f"(t = {frame / constants.FRAME_RATE_HZ:.2f} s)",
      fontsize=8,
  )
  ax.tick_params(labelsize=6)


def render_gif(
    rec, scene: dict, frames, preds=None, fps: float = 5.0, width_in: float = 16.0, x_range=None
) -> bytes:
  """GIF bytes of `frames` of recording `rec` (`data.highd.Recording`) with `scene`
  (`data.frames.scene`) and the predictions `preds` (`inference.recording.
  VehiclePredictions`, drawn at their own frames; None = vehicles only); `x_range` (x0, x1)
  the image-frame section drawn, m (None: the whole road)."""
  frames = [int(f) for f in frames]
  if not frames:
    raise ValueError("render_gif: no frames to draw")
  if x_range is None:
    centres = frames_lib.image_centre(rec, np.arange(len(rec.frame)))
    x_range = (float(centres[:, 0].min()) - 10.0, float(centres[:, 0].max()) + 10.0)
  x_range = tuple(float(x) for x in x_range)
  lanes = np.concatenate([scene["upper"], scene["lower"]])
  y_range = (float(lanes.min()) - 2.0, float(lanes.max()) + 2.0)
  height_in = max(1.5, width_in * (y_range[1] - y_range[0]) / (x_range[1] - x_range[0]) + 0.6)
  fig, ax = plt.subplots(figsize=(width_in, height_in), dpi=100)
  try:
    movie = mpl_animation.FuncAnimation(
        fig,
        lambda f: _draw_frame(ax, rec, scene, f, preds, x_range, y_range),
        frames=frames,
        blit=False,
    )
    with tempfile.TemporaryDirectory() as tmp:
      path = Path(tmp) / "scene.gif"
      movie.save(path, writer=mpl_animation.PillowWriter(fps=fps))
      return path.read_bytes()
  finally:
    plt.close(fig)


def write_clip(
    predictor,
    data_dir,
    recording_id: int,
    path,
    start_s: float = 10.0,
    seconds: float = 1.0,
    every: int = 5,
    section_m: float = 300.0,
    num_samples: int | None = 9,
    seed: int = 0,
) -> dict:
  """Writes to `path` (atomic) a GIF of `seconds` of recording `recording_id` of `data_dir`
  from `start_s` after its first frame, at every `every`-th frame: the middle `section_m`
  metres of the road and the hypotheses of every vehicle there (`predictor`, a
  `Predictor`, with `num_samples` samples; None = its own). The defaults keep `make demo`'s
  clip short (about 100 predictions). Returns the prediction summary
  (`inference.recording.predict_frames`)."""
  if num_samples is not None:
    predictor = dataclasses.replace(
        predictor, sampling=dataclasses.replace(predictor.sampling, num_samples=num_samples)
    )
  rec = highd.read_recording(data_dir, recording_id)
  first, last = frames_lib.frame_range(rec)
  begin = min(last, first + round(start_s * constants.FRAME_RATE_HZ))
  end = min(last, begin + round(seconds * constants.FRAME_RATE_HZ))
  window = list(range(begin, end + 1, every))
  x = frames_lib.image_centre(rec, np.arange(len(rec.frame)))[:, 0]
  middle = 0.5 * (x.min() + x.max())
  section = (middle - section_m / 2, middle + section_m / 2)
  preds, summary = recording.predict_frames(
      predictor, rec, window, seed=seed, every=every, section=section
  )
  gif = render_gif(
      rec,
      frames_lib.scene(data_dir, recording_id),
      window,
      preds,
      fps=constants.FRAME_RATE_HZ / every,
      x_range=section,
  )
  atomic.write_bytes(path, gif)
  return summary
