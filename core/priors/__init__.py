"""Priors over chrome balls (the 'guidance' of threestudio): they see 2D images and ball
geometry, never the light field being optimised."""
from core.priors.base import Prior, PriorRequest, ProbeGeometry, PriorError

__all__ = ["Prior", "PriorRequest", "ProbeGeometry", "PriorError"]
