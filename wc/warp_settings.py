"""Warp's process-wide settings for WorldContact, applied on import: import this module before `newton` or any module
that defines warp kernels, since a kernel module takes its options when it is defined.

- No backward kernels: nothing here differentiates through warp (the learned models are torch), and compiling the
  adjoints of Newton's kernels doubled the cold CPU compile (a lift_handle episode: 224 s of compilation with them,
  115 s without; the episodes are identical, docs/measurements.md).
- Quiet module loads; warnings still shown.
- Deterministic atomics when WC_DETERMINISTIC asks for them (wc.determinism).
"""

import warp as wp

from wc import determinism

wp.config.enable_backward = False
wp.config.quiet = True
wp.config.log_level = wp.LOG_WARNING
determinism.apply(determinism.requested_mode())
