"""The cell's own calibration jobs: the hand-eye job, the part placement estimate, the reverification job.

* :func:`run_hand_eye` (``cell calibrate hand-eye CELL.toml``): stations around the calibration
  artefact chosen for a well-conditioned hand-eye (D-optimal on the predicted information, among
  the candidates the robot reaches without collision), ordered and collision-checked like an
  inspection's; per image: dots detected, identified, centred (eccentricity), exterior orientation
  by Faugeras-Toscani refined by resection; AX = XB by every closed-form method; then the joint
  refinement on all observations with its covariance. ``flange_from_cam`` and the date go into
  the cell file; everything is archived under ``<archive>/calibration/<id>/``.
* :func:`estimate_part_placement`: a few images of the part's coded targets, then the placement
  adjusted on every identified dot with the hand-eye held fixed.
* :func:`run_reverification` (after VDI/VDE 2634 part 1): the scale bar in several positions;
  its two targets triangulated in the robot base frame from the robot's poses and the hand-eye
  (the cell measuring as a whole); the length measurement error of each position against
  ``E_MPE``; archived. :func:`calibration_status` is what an inspection report states.
"""
