"""Every test sees 8 fake CPU devices, fp32, no accelerator."""

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")
_flag = "--xla_force_host_platform_device_count=8"
if _flag not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + _flag).strip()

import jax  # noqa: E402  (must come after the flags above)

jax.config.update("jax_num_cpu_devices", 8)

from hypothesis import settings  # noqa: E402

# jit dispatch makes single examples slow to start; deadlines would flake, not find bugs.
settings.register_profile("jaxdrive", deadline=None, max_examples=60, derandomize=True)
settings.load_profile("jaxdrive")
