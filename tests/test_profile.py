"""Profile loading and validation: every bad input names file, line and column."""

import numpy as np
import pytest

from solvers import ProfileError, ground_z, load_profile, make_profile

MAT_HEADER = "zone,Kn,Kt,roughness_m,rolling_friction_deg,phi_deg\n"
MAT_OK = MAT_HEADER + "a,0.41,0.87,2.0,30,30\n"


def _write(tmp_path, profile_text, materials_text=MAT_OK):
    p = tmp_path / "site_profile.csv"
    p.write_text(profile_text)
    (tmp_path / "site_materials.csv").write_text(materials_text)
    return str(p)


def test_postignano_profile_loads_and_matches_paper_geometry():
    prof = load_profile("data/postignano_profile.csv")
    x, z = np.asarray(prof.x_m), np.asarray(prof.z_m)
    angles = np.degrees(np.arctan(-np.diff(z) / np.diff(x)))
    np.testing.assert_allclose(angles, [75.0, 40.0, 6.0], atol=0.01)
    drop = float(ground_z(prof, 0.0) - ground_z(prof, 250.0))
    assert abs(np.degrees(np.arctan(drop / 250.0)) - 28.0) < 1.0  # "average dip of about 28 deg"
    assert prof.segment_zone_names() == ["cliff", "talus", "lower"]


@pytest.mark.parametrize("text, needle", [
    ("x_m,z_m,zone\n0,10,a\n", "at least 2 vertices"),
    ("x_m,z_m,zone\n0,10,a\n5,4,a\n5,3,\n", "line 4: column 'x_m'"),
    ("x_m,z_m,zone\n0,10,a\n-1,4,\n", "overhangs"),
    ("x_m,z_m,zone\n0,nan,a\n5,4,\n", "line 2: column 'z_m'"),
    ("x_m,z_m,zone\n0,inf,a\n5,4,\n", "finite"),
    ("x_m,z_m,zone\n0,abc,a\n5,4,\n", "expected a number"),
    ("x_m,z_m,zone\n0,10,b\n5,4,\n", "line 2: column 'zone': unknown zone 'b'"),
    ("x_m,zone\n0,a\n5,\n", "missing column(s) z_m"),
    ("", "empty file"),
])
def test_bad_profiles_are_rejected_with_location(tmp_path, text, needle):
    path = _write(tmp_path, text)
    with pytest.raises(ProfileError) as exc:
        load_profile(path)
    assert needle in str(exc.value)
    assert "site_profile.csv" in str(exc.value)


@pytest.mark.parametrize("mat, needle", [
    (MAT_HEADER + "a,1.2,0.87,2.0,30,30\n", "column 'Kn': restitution must lie in (0, 1]"),
    (MAT_HEADER + "a,0.41,0.0,2.0,30,30\n", "column 'Kt'"),
    (MAT_HEADER + "a,0.41,0.87,-1,30,30\n", "roughness"),
    ("zone,Kn,Kt\na,0.4,0.8\n", "missing column(s)"),
    (MAT_HEADER + "a,0.41,0.87,2.0,30,30\na,0.41,0.87,2.0,30,30\n", "duplicate zone"),
])
def test_bad_materials_are_rejected_with_location(tmp_path, mat, needle):
    path = _write(tmp_path, "x_m,z_m,zone\n0,10,a\n5,4,\n", mat)
    with pytest.raises(ProfileError) as exc:
        load_profile(path)
    assert needle in str(exc.value)
    assert "site_materials.csv" in str(exc.value)


def test_missing_file_is_named(tmp_path):
    with pytest.raises(ProfileError, match="nowhere_profile.csv: file not found"):
        load_profile(str(tmp_path / "nowhere_profile.csv"))


def test_with_materials_validates_overrides():
    prof = load_profile("data/postignano_profile.csv")
    new = prof.with_materials(Kn=0.3)
    assert np.allclose(np.asarray(new.Kn), 0.3)
    with pytest.raises(ProfileError, match="restitution"):
        prof.with_materials(Kt=1.5)


def test_make_profile_rejects_unknown_zone():
    with pytest.raises(ProfileError, match="unknown zone"):
        make_profile([0, 1], [1, 0], ["q"], {"a": dict(Kn=0.4, Kt=0.8, roughness_m=0,
                                                        rolling_friction_deg=30, phi_deg=30)})
