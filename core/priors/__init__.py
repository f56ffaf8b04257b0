"""Priors over chrome balls (the 'guidance' of threestudio): they see 2D images and ball
geometry, never the light field being optimised. Registered by name (core.priors.registry);
the built-in light priors register here, the diffusion prior on first use, the simulator's
oracle when core.sim.oracle is imported."""
from core.priors.base import Prior, PriorCapabilities, PriorConfig, PriorError, PriorRequest, ProbeGeometry
from core.priors.known import KnownRadiancePrior  # registers "known"
from core.priors.registry import build_prior, job_prior_names, prior_names, register_prior
from core.priors.reprojection import ReprojectionPrior  # registers "reprojection"

__all__ = [
    "KnownRadiancePrior", "Prior", "PriorCapabilities", "PriorConfig", "PriorError", "PriorRequest", "ProbeGeometry",
    "ReprojectionPrior", "build_prior", "job_prior_names", "prior_names", "register_prior",
]
