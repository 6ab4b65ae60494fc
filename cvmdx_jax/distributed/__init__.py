"""Several processes of one run: `launch` joins the run (`initialize_distributed`, re-exported
by `cvmdx_jax.sharding`), `coordination` hosts `jax.distributed`'s coordination service apart
from process 0."""
