import os
import sys

import jax

jax.config.update("jax_enable_x64", True)  # the reference runs in float64; splatsearch casts to float32
sys.path.insert(0, os.path.dirname(__file__))
