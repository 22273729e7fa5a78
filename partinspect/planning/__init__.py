"""Acquisition planning: predicted uncertainties before anything is measured.

``inspect plan`` answers, from the CAD model, the rig's calibration and the
tolerances alone: with the part in this pose, which characteristics could
the measurement decide, and in which pose could it decide them all?

- :mod:`.edge_model`: the standard uncertainty of one detected edge point
  from image noise, edge contrast, optical blur and the edge filter's
  scale, and the detector's point spacing;
- :mod:`.predict`: the CAD edges projected into both cameras at a pose,
  turned into the edge points the detector would give, and run through the
  measurement chain's own covariance code (2D fits, correspondences,
  two-view 3D fits, calibration, registration, characteristic evaluation);
- :mod:`.search`: poses of the part on the fixture (rotation about the
  fixture's axis and tilt) and the search for one where every
  characteristic is decidable;
- :mod:`.report`: the terminal table and the HTML page.
"""
