"""Newton source simulator (kernel-load chatter off: set before warp initialises)."""

import warp as wp

wp.config.quiet = True
