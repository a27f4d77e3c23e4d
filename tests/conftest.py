import jax

# Tests work in float64 unless they cast to float32 themselves; jaxest never flips this on import.
jax.config.update("jax_enable_x64", True)
