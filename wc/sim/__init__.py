"""Newton source simulator (warp's settings from wc.warp_settings, applied before Newton defines its kernels)."""

import wc.warp_settings  # noqa: F401
