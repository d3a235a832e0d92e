"""Newton source simulator (warp's per-kernel load chatter off; warnings still shown)."""

import warp as wp

wp.config.quiet = True
wp.config.log_level = wp.LOG_WARNING
