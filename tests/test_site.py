"""Site files (nothing site-specific in defaults): where they are found,
what they give, bad ones refused, and calib.hazard reporting at the site's
station of interest or, without one, at the profile's last station."""

from __future__ import annotations

import contextlib
import io
import json
import shutil

import pytest
from test_hazard_cli import SMALL
from test_hazard_fixtures import write_calibration

from calib.files.site import SiteError, load_site, site_path
from calib.hazard.__main__ import main as hazard_main


def test_site_file_names():
    assert site_path("data/postignano_profile.csv") == "data/postignano_site.json"
    assert site_path("data/tschamut2014/profile.csv") == "data/tschamut2014/profile_site.json"
    assert site_path("a/slope.csv") == "a/slope_site.json"


def test_shipped_sites():
    post = load_site("data/postignano_profile.csv")
    assert (post.station_x_m, post.station_label) == (230.0, "road")
    assert dict(post.alpha_reference) == {0.2: 0.90, 0.9: 0.43, 1.8: 0.30}
    assert post.dem_max_time_s == 200.0 and "98-164 s" in post.dem_max_time_source
    tsch = load_site("data/tschamut2014/profile.csv")
    assert tsch.station_x_m is None and tsch.alpha_reference == () and tsch.name
    assert tsch.dem_max_time_s is None and tsch.dem_max_time_source == ""


def test_no_site_file_is_an_empty_site(tmp_path):
    s = load_site(str(tmp_path / "profile.csv"))
    assert s.station_x_m is None and s.alpha_reference == () and s.path is None


@pytest.mark.parametrize("doc, needle", [
    ("{", "not a readable JSON"),
    ('{"station_of_interest": {"label": "road"}}', "'station_of_interest'"),
    ('{"station_of_interest": {"x_m": "far"}}', "station_of_interest.x_m"),
    ('{"alpha_reference": {"L_m": [0.2], "alpha": [1.5]}}', "alpha_reference.alpha"),
    ('{"alpha_reference": {"L_m": [0.2, 0.9], "alpha": [0.5]}}', "one length"),
    ('{"dem_max_time_s": 200}', "'dem_max_time_source': expected text saying where"),
    ('{"dem_max_time_source": "measured"}', "'dem_max_time_source': given without"),
    ('{"dem_max_time_s": 0, "dem_max_time_source": "x"}', "'dem_max_time_s': expected a "
                                                          "finite number in [1, 100000]"),
])
def test_bad_site_files_name_file_and_key(tmp_path, doc, needle):
    (tmp_path / "profile_site.json").write_text(doc)
    with pytest.raises(SiteError, match="site.json") as e:
        load_site(str(tmp_path / "profile.csv"))
    assert needle in str(e.value)


def _run(cal, out, *extra):
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert hazard_main([cal, *SMALL, "--out", str(out), *extra]) == 0
    return buf.getvalue(), (out / "summary.txt").read_text()


def test_hazard_reports_at_the_site_station_or_the_last_station(tmp_path):
    """Same profile geometry: next to its site file the summary reports at the
    road (230 m); copied without one, at the last station (300 m), and says so;
    a site file naming another station and label is followed."""
    cal = write_calibration(tmp_path, crsp_posterior=None)
    printed, summary = _run(cal, tmp_path / "a")
    assert "road at x = 230 m" in summary and "P(reach road)" in summary

    bare = tmp_path / "bare"
    bare.mkdir()
    shutil.copy("data/postignano_profile.csv", bare / "profile.csv")
    shutil.copy("data/postignano_materials.csv", bare / "profile_materials.csv")
    cal2 = write_calibration(bare, crsp_posterior=None, profile=str(bare / "profile.csv"))
    printed, summary = _run(cal2, bare / "out")
    assert "no station of interest" in printed
    assert f"no site file {bare / 'profile_site.json'} gives one" in printed
    assert "last station at x = 300 m" in summary

    (bare / "profile_site.json").write_text(json.dumps({"name": "a site without a road"}))
    printed, summary = _run(cal2, bare / "out1")
    assert (f"the site file {bare / 'profile_site.json'} gives no station_of_interest"
            in printed), printed
    assert "last station at x = 300 m" in summary

    (bare / "profile_site.json").write_text(json.dumps(
        {"station_of_interest": {"x_m": 150.0, "label": "house"}}))
    _, summary = _run(cal2, bare / "out2")
    assert "house at x = 150 m" in summary and "P(reach house)" in summary
