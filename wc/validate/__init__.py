"""Physical and visual checks of simulated episodes (stage `validate`)."""

from wc.validate.config import ValidateConfig
from wc.validate.predicates import PREDICATES, Episode, first_failure

__all__ = ["PREDICATES", "Episode", "ValidateConfig", "first_failure"]
