"""Work in progress (being written in this session)."""
import mitsuba as mi


class _WIP(mi.ad.integrators.common.ADIntegrator):
    def sample(self, mode, scene, sampler, ray, δL=None, state_in=None, active=True, **kw):
        raise NotImplementedError("integrator under construction")


VSRDSilhouetteIntegrator = SDFTracerIntegrator = _WIP
