"""The viewing sphere of a part too large to frame in one image within the camera's depth of field: planned from
within it, the stations looking at regions of the part, said; an empty range is one error naming the keys."""
from __future__ import annotations

import numpy as np
import pytest

from calibration.errors import JobSpecError
from cell.loadedjob import load
from cell.setup import REGION_OFFSET_FRACTION, planner_options, viewing_sphere
from planning.stations import ViewingSphere
from tests.jobutil import job_variant


def test_the_example_is_framed_whole_and_nothing_is_said(tmp_path):
    job = load(job_variant(tmp_path / "job"))
    sphere, note = viewing_sphere(job)
    r = job.part.radius
    framed = ViewingSphere.for_part(job.part, job.intrinsics)
    assert note is None
    assert np.isclose(sphere.distance_min_m, framed.distance_min_m)
    assert np.isclose(sphere.distance_max_m, job.spec.camera.far * job.spec.scale - 0.5 * r)
    assert sphere.max_offset_m == framed.max_offset_m
    assert planner_options(job).sphere == sphere


def test_a_depth_of_field_too_short_to_frame_the_part_plans_regions_of_it(tmp_path):
    # the bracket (403 mm across) fills the image from 489 mm; far = 560 mm keeps the centre within 459 mm
    job = load(job_variant(tmp_path / "job", {"camera": {"far": 560.0}}))
    sphere, note = viewing_sphere(job)
    r, k = job.part.radius, job.spec.scale
    assert note is not None and "look at regions of it" in note and "beyond the camera's depth of field" in note
    assert np.isclose(sphere.distance_max_m, 0.560 - 0.5 * r)
    assert np.isclose(sphere.distance_min_m, max(job.spec.camera.near * k + 0.5 * r, r + 0.05))
    assert sphere.distance_min_m < sphere.distance_max_m < ViewingSphere.for_part(job.part, job.intrinsics).distance_min_m
    assert np.isclose(sphere.max_offset_m, REGION_OFFSET_FRACTION * r)


@pytest.mark.parametrize("changes", [{"camera": {"far": 480.0}},
                                     {"camera": {"far": 560.0}, "planning": {"distance_min": 500.0}}])
def test_no_distance_in_the_depth_of_field_is_one_error_naming_the_keys(tmp_path, changes):
    job = load(job_variant(tmp_path / "job", changes))
    with pytest.raises(JobSpecError, match=r"depth of field.*\[camera\] near / far .*\[planning\] distance_min"):
        viewing_sphere(job)
