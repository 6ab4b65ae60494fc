"""Several processes of one run: `coordination` hosts `jax.distributed`'s coordination
service apart from process 0 (`cvmdx_jax.sharding` joins the run)."""
