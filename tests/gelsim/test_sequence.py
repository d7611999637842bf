"""Contact location labels of a sequence (gelsim.sequence): centroid and bounding box of the contact mask per frame."""
from __future__ import annotations

import numpy as np

from gelsim.fabrics import load_catalog
from gelsim.fidelity import get_fidelity
from gelsim.motion import sample_motion
from gelsim.sensor import load_profile
from gelsim.sequence import SequenceOptions, render_sequence
from gelsim.sinks import drain


def test_sequence_labels_locate_the_contact():
    profile = load_profile("vitac").with_resolution(160, 120)
    fid = get_fidelity("fast")
    T, pre = 8, 3
    motion = sample_motion("twist", 5, frames=(T, T), precontact=(pre, pre))
    lab, _ = drain(render_sequence(load_catalog()[21], motion, profile, fid, seed=5,
                                   options=SequenceOptions(outputs={"imprint"})))
    cen, box = lab["contact_centroid_px"], lab["contact_bbox_px"]
    assert cen.shape == (T, 2) and box.shape == (T, 4)
    assert cen.dtype == np.float32 and box.dtype == np.float32
    has = lab["contact_area_mm2"] > 0
    assert has.sum() >= 3 and not has[:pre].any()
    # NaN exactly where there is no contact
    assert np.isnan(cen[~has]).all() and np.isnan(box[~has]).all()
    assert np.isfinite(cen[has]).all() and np.isfinite(box[has]).all()
    h, w = profile.shape
    for c, b, a in zip(cen[has], box[has], lab["contact_area_mm2"][has]):
        assert b[0] <= c[0] <= b[2] and b[1] <= c[1] <= b[3]
        assert -0.5 <= b[0] < b[2] <= w - 0.5 and -0.5 <= b[1] < b[3] <= h - 0.5
        # the box holds the whole contact area
        box_mm2 = (b[2] - b[0]) * (b[3] - b[1]) * profile.image.mm_per_px ** 2
        assert box_mm2 >= a * (1 - 1e-4)
