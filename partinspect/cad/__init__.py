"""The CAD side: STEP loading, the feature inventory, meshes, deviated parts.

Modules (each imports cadquery/OCP only inside its functions, so importing
them is cheap):

- `step`: ``load_step`` / ``save_step``, STEP files <-> solids in mm.
- `features`: ``inventory`` of line, circle and arc edges with stable ids;
  ``nearest_feature`` for ``at:`` selectors.
- `mesh`: ``tessellate``, a triangle mesh labelled by CAD face.
- `deviate`: ``deviate`` / ``parse_deviation``, parts with holes resized or
  moved, for synthetic test renders.
- `registration`: ``register``, the part's pose from measured circles and
  lines, with its covariance; its hypothesis search is `pose_search`, its
  weighted least-squares fit `pose_refine`.
"""
