"""Named views of a measured feature's parameter vector and covariance, part frame."""

import numpy as np

__all__ = ["FeatureParams"]


class FeatureParams:
    """Named views of a part-frame feature's ``params`` and ``param_cov`` (circles and lines).

    Shared by :class:`partinspect.cad.registration.PartFeature` and the
    fused features of several views (:mod:`partinspect.tolerances.fusion`):
    circles ``(center, normal, radius)``, lines ``(point, direction)``, mm.
    """

    @property
    def center(self):
        return self.params[:3] if self.kind == "circle" else None

    @property
    def normal(self):
        return self.params[3:6] if self.kind == "circle" else None

    @property
    def radius(self):
        return float(self.params[6]) if self.kind == "circle" else None

    @property
    def point(self):
        return self.params[:3] if self.kind == "line" else None

    @property
    def direction(self):
        return self.params[3:6] if self.kind == "line" else None

    @property
    def covariance(self):
        """3x3 covariance of the centre (circles) or point (lines), mm^2."""
        return self.param_cov[:3, :3]

    @property
    def normal_cov(self):
        return self.param_cov[3:6, 3:6] if self.kind == "circle" else None

    @property
    def direction_cov(self):
        return self.param_cov[3:6, 3:6] if self.kind == "line" else None

    @property
    def radius_std(self):
        return float(np.sqrt(self.param_cov[6, 6])) if self.kind == "circle" else None
