"""Build a prior by name. Heavy or optional priors are imported lazily, so a missing
optional dependency only matters to the user who asked for that prior."""
from __future__ import annotations

import importlib

from core.priors.base import Prior, PriorError

PRIOR_NAMES = ("reprojection", "known", "diffusion", "oracle")


def build_prior(name: str, weights: str | None = None, **kw) -> Prior:
    """'reprojection' (default, weights-free), 'known' (kw: fn), 'diffusion' (weights = local
    model dir; kw: device, dtype, profile), 'oracle' (simulator ground truth; kw passed to core.sim.oracle)."""
    if name == "reprojection":
        from core.priors.reprojection import ReprojectionPrior

        return ReprojectionPrior(**kw)
    if name == "known":
        from core.priors.known import KnownRadiancePrior

        if "fn" not in kw:
            raise PriorError("prior 'known' needs fn=callable(x, t, d) -> radiance")
        return KnownRadiancePrior(**kw)
    if name == "diffusion":  # raises PriorError without weights
        return _optional("core.priors.diffusion.prior", "the diffusion prior").build_diffusion_prior(weights, **kw)
    if name == "oracle":
        return _optional("core.sim.oracle", "the simulator's oracle prior").OracleSimPrior(**kw)
    raise PriorError(f"unknown prior {name!r}; choose one of {', '.join(PRIOR_NAMES)}")


def _optional(module_name: str, what: str):
    try:
        return importlib.import_module(module_name)
    except ImportError as exc:
        raise PriorError(f"{what} is unavailable ({module_name} could not be imported: {exc})") from exc
