"""Profiles cut from a raster (terrain/raster.py, terrain/plan_line.py, python -m terrain.cut)."""

import json
import os
import sys

import numpy as np
import pytest
from cli_run import run_cli, run_module

from solvers import load_profile
from terrain.cut import main
from terrain.plan_line import Polyline, mean_fall_line, read_line, read_profile_trace
from terrain.raster import (
    Raster,
    RasterError,
    cut_profile,
    parse_zones,
    read_ascii_grid,
    read_raster,
)

PLANE = (12.0, -0.3, 0.45)  # z = a + b east + c north


def _plane(e, n):
    a, b, c = PLANE
    return a + b * np.asarray(e) + c * np.asarray(n)


def _write_grid(path, z_north_first, xll=100.0, yll=200.0, cell=5.0, corner=True, nodata=-9999,
                extra_header=""):
    nrows, ncols = z_north_first.shape
    kind = "corner" if corner else "center"
    head = (f"ncols {ncols}\nnrows {nrows}\nxll{kind} {xll}\nyll{kind} {yll}\n"
            f"cellsize {cell}\nNODATA_value {nodata}\n{extra_header}")
    rows = "\n".join(" ".join(f"{v:.10g}" for v in row) for row in z_north_first)
    path.write_text(head + rows + "\n")
    return str(path)


def _plane_grid(nrows=8, ncols=10, xll=100.0, yll=200.0, cell=5.0):
    """Plane values at cell centres, rows north first (as in the file)."""
    e = xll + (np.arange(ncols) + 0.5) * cell
    n = yll + (np.arange(nrows)[::-1] + 0.5) * cell
    return _plane(e[None, :], n[:, None])


def test_bilinear_sampling_is_exact_on_a_plane(tmp_path):
    grid = read_ascii_grid(_write_grid(tmp_path / "plane.asc", _plane_grid()))
    (w, e), (s, n) = grid.east_range_m, grid.north_range_m
    assert (w, e, s, n) == (102.5, 147.5, 202.5, 237.5)  # cell centres, xllcorner + c/2
    rng = np.random.default_rng(0)
    pe, pn = rng.uniform(w, e, 500), rng.uniform(s, n, 500)
    pe[:4], pn[:4] = [w, e, w, e], [s, s, n, n]  # the corners of the data area
    np.testing.assert_allclose(grid.sample(pe, pn), _plane(pe, pn), rtol=0, atol=1e-10)


def test_xllcenter_and_xllcorner_place_the_cells_alike(tmp_path):
    z = _plane_grid()
    a = read_ascii_grid(_write_grid(tmp_path / "a.asc", z, xll=100.0, yll=200.0))
    b = read_ascii_grid(_write_grid(tmp_path / "b.asc", z, xll=102.5, yll=202.5, corner=False))
    assert (a.east0_m, a.north0_m) == (b.east0_m, b.north0_m) == (102.5, 202.5)
    # the first file row is the northernmost: its first value sits at the NW centre
    assert a.sample(102.5, 237.5) == pytest.approx(z[0, 0], abs=1e-12)
    assert a.sample(147.5, 202.5) == pytest.approx(z[-1, -1], abs=1e-12)


def _read(path):
    with open(path) as fh:
        return fh.read()


def _line(e, n):
    return Polyline(np.array(e, float), np.array(n, float), "test-line")


def test_cut_along_a_bent_line_follows_the_plane_and_unrolls_x():
    grid = Raster(_plane_grid()[::-1].copy(), 102.5, 202.5, 5.0, "mem")
    line = _line([105, 135, 135], [230, 230, 205.5])  # 30 m east, then 24.5 m south
    cut = cut_profile(grid, line, 1.0, parse_zones("a:0:30,b:30:"))
    assert cut.x_m[0] == 0 and cut.x_m[-1] == pytest.approx(54.5)
    assert 30.0 in cut.x_m  # the bend is a vertex
    np.testing.assert_allclose(np.diff(cut.x_m)[:30], 1.0)
    np.testing.assert_allclose(cut.z_m, _plane(cut.east_m, cut.north_m), atol=1e-10)
    k = int(np.flatnonzero(cut.x_m == 30.0)[0])
    assert (cut.east_m[k], cut.north_m[k]) == (135, 230)
    assert set(cut.zone[:k]) == {"a"} and set(cut.zone[k:]) == {"b"}
    assert cut.x_m[-1] - cut.x_m[-2] == pytest.approx(0.5)  # the end is kept


def test_no_station_closer_than_a_tenth_of_a_step_to_a_vertex_or_the_end():
    grid = Raster(_plane_grid()[::-1].copy(), 102.5, 202.5, 5.0, "mem")
    cut = cut_profile(grid, _line([105, 115.05, 115.05], [230, 230, 220.02]), 1.0)
    assert np.diff(cut.x_m).min() >= 0.1
    np.testing.assert_allclose(cut.x_m[9:12], [9.0, 10.05, 11.0])  # 10 dropped for the bend
    assert cut.x_m[-1] == pytest.approx(20.03) and cut.x_m[-2] == 19.0  # 20 dropped


def test_nodata_under_the_line_is_refused_with_its_distance():
    z = _plane_grid()[::-1].copy()
    z[3, 4] = np.nan  # centre (122.5, 217.5)
    grid = Raster(z, 102.5, 202.5, 5.0, "dem.asc")
    with pytest.raises(RasterError, match=r"dem.asc: NODATA under the line .* at 16.00 m along"):
        cut_profile(grid, _line([102.5, 147.5], [217.5, 217.5]))  # weight > 0 from e = 118
    cut_profile(grid, _line([102.5, 147.5], [227.5, 227.5]))  # two rows away: fine


@pytest.mark.parametrize("e, n, where", [
    ([90.0, 140.0], [220.0, 220.0], "at 0.00 m"),       # starts west of the data area
    ([105.0, 160.0], [220.0, 220.0], "at 43.00 m"),     # runs out east (edge at 147.5)
    ([105.0, 105.0], [220.0, 300.0], "at 18.00 m"),     # runs out north (edge at 237.5)
])
def test_line_outside_the_raster_is_refused(e, n, where):
    grid = Raster(_plane_grid()[::-1].copy(), 102.5, 202.5, 5.0, "dem.asc")
    with pytest.raises(RasterError, match="dem.asc: the line .* leaves the raster's data area "
                       + where):
        cut_profile(grid, _line(e, n))


def test_line_shorter_than_one_step_is_refused():
    grid = Raster(_plane_grid()[::-1].copy(), 102.5, 202.5, 5.0, "dem.asc")
    with pytest.raises(RasterError, match="test-line: the line is 0.9 m long, shorter than one "
                                          "step"):
        cut_profile(grid, _line([110, 110.9], [210, 210]), step_m=1.0)
    assert len(cut_profile(grid, _line([110, 111], [210, 210]), step_m=1.0).x_m) == 2


@pytest.mark.parametrize("header, rows, needle", [
    ("ncols 3\nxllcorner 0\nyllcorner 0\ncellsize 1\n", "1 2 3\n1 2 3\n", "missing 'nrows'"),
    ("ncols 3\nnrows 2\nxllcorner 0\nxllcenter 0\nyllcorner 0\ncellsize 1\n", "1 2 3\n1 2 3\n",
     "exactly one of 'xllcorner' and 'xllcenter'"),
    ("ncols 3\nnrows 2\nxllcorner 0\nyllcorner 0\ncellsize 1\nrotation 5\n", "1 2 3\n1 2 3\n",
     "line 6: unknown header key 'rotation'"),
    ("ncols 3\nnrows 2\nxllcorner 0\nyllcorner 0\ncellsize abc\n", "1 2 3\n1 2 3\n",
     "line 5: header key 'cellsize': expected a number"),
    ("ncols 3\nnrows 2\nxllcorner 0\nyllcorner 0\ncellsize -1\n", "1 2 3\n1 2 3\n",
     "'cellsize': expected a positive size"),
    ("ncols 3\nnrows 2\nxllcorner 0\nyllcorner 0\ncellsize 1\n", "1 2 3\n1 2\n",
     "line 7: grid row 2: expected ncols = 3 values, got 2"),
    ("ncols 3\nnrows 2\nxllcorner 0\nyllcorner 0\ncellsize 1\n", "1 2 3\n1 x 3\n",
     "line 7: column 2: expected a finite number, got 'x'"),
    ("ncols 3\nnrows 2\nxllcorner 0\nyllcorner 0\ncellsize 1\n", "1 2 3\n",
     "expected nrows = 2 grid rows, got 1"),
    ("ncols 3\nnrows 2\nxllcorner 0\nyllcorner 0\ncellsize 1\n", "1 2 3\n1 2 3\n4 5 6\n",
     "line 8: more grid rows than nrows = 2"),
    ("", "", "empty file"),
])
def test_malformed_grids_are_refused_with_line_and_column(tmp_path, header, rows, needle):
    p = tmp_path / "bad.asc"
    p.write_text(header + rows)
    with pytest.raises(RasterError) as exc:
        read_ascii_grid(str(p))
    assert needle in str(exc.value) and "bad.asc" in str(exc.value)


def test_geotiff_without_rasterio_says_so(tmp_path, monkeypatch):
    tif = tmp_path / "dem.tif"
    tif.write_bytes(b"II*\x00")
    monkeypatch.setitem(sys.modules, "rasterio", None)  # import rasterio -> ImportError
    with pytest.raises(RasterError, match="dem.tif: reading a GeoTIFF needs the optional "
                                          "package rasterio"):
        read_raster(str(tif))


def test_projection_onto_a_known_line():
    line = _line([0, 10, 10], [0, 0, -20])  # east 10 m, then south 20 m
    along, off = line.project([5, 12, 7, 10, -3, 10], [2, -5, -1, -26, 0, -21])
    np.testing.assert_allclose(along, [5, 15, 7, 36, -3, 31])
    # positive to the left of travel: north of the first leg, east of the second
    np.testing.assert_allclose(off, [2, 2, -1, 0, 0, 0], atol=1e-12)


def test_mean_fall_line_runs_from_mean_release_to_mean_stop_with_margins():
    line = mean_fall_line([0, 2], [10, 10], [1, 1], [0, -2], margin_m=5.0)
    # mean release (1, 10), mean stop (1, -1): due south, extended 5 m both ways
    np.testing.assert_allclose(line.east_m, [1, 1])
    np.testing.assert_allclose(line.north_m, [15, -6])


def test_line_files_csv_and_geojson(tmp_path):
    (tmp_path / "l.csv").write_text("id,x,y\na,1,2\nb,4,6\n")
    (tmp_path / "l.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {},
         "geometry": {"type": "LineString", "coordinates": [[1, 2, 9], [4, 6, 9]]}}]}))
    a, b = read_line(str(tmp_path / "l.csv")), read_line(str(tmp_path / "l.geojson"))
    np.testing.assert_array_equal(a.east_m, b.east_m)
    np.testing.assert_array_equal(a.north_m, b.north_m)
    assert a.length_m == 5.0
    (tmp_path / "bad.csv").write_text("x,y\n1,2\n4,oops\n")
    with pytest.raises(RasterError, match="bad.csv: line 3: column 'y': expected a number"):
        read_line(str(tmp_path / "bad.csv"))
    (tmp_path / "two.geojson").write_text(json.dumps({"type": "MultiPoint", "coordinates": []}))
    with pytest.raises(RasterError, match="exactly one GeoJSON LineString, found 0"):
        read_line(str(tmp_path / "two.geojson"))


def test_uncovered_zone_is_refused():
    grid = Raster(_plane_grid()[::-1].copy(), 102.5, 202.5, 5.0, "dem.asc")
    with pytest.raises(RasterError, match="no zone covers the segment at 10.50 m"):
        cut_profile(grid, _line([105, 140], [210, 210]), 1.0, parse_zones("a:0:10,b:11:"))
    with pytest.raises(RasterError, match="overlaps"):
        parse_zones("a:0:10,b:5:")


# ---------------------------------------------------------------- command line


def _cli(argv, capsys):
    return run_cli(main, argv, capsys)


def _setup(tmp_path, nodata_at=None):
    z = _plane_grid()
    if nodata_at is not None:
        z[nodata_at] = -9999
    grid = _write_grid(tmp_path / "dem.asc", z)
    (tmp_path / "line.csv").write_text("east_m,north_m\n105,230\n145,205\n")
    return grid, str(tmp_path / "line.csv"), str(tmp_path / "out" / "p.csv")


def test_cli_writes_a_profile_that_loads(tmp_path, capsys):
    grid, line, out = _setup(tmp_path)
    os.makedirs(os.path.dirname(out))
    rc, stdout, err = _cli([grid, "--line", line, "--step-m", "2",
                            "--zones", "up:0:20,down:20:", "--out", out], capsys)
    assert rc == 0, err
    prof = load_profile(out)  # finds p_materials.csv
    assert prof.zone_names == ("up", "down")
    x, trace = read_profile_trace(out)
    np.testing.assert_allclose(np.asarray(prof.z_m), _plane(trace.east_m, trace.north_m),
                               atol=1e-4)
    info = json.loads(_read(out[:-4] + ".cut.json"))
    assert info["n_vertices"] == len(x) and "raster's own" in info["raster_crs"]
    assert "zone up" in stdout


@pytest.mark.parametrize("case, needle", [
    ("nodata", "NODATA under the line"),
    ("outside", "leaves the raster's data area"),
    ("short", "shorter than one step"),
    ("bad_grid", "grid row 2: expected ncols = 10 values"),
    ("materials", "no row for zone(s) down"),
])
def test_cli_bad_input_exits_2_and_writes_nothing(tmp_path, capsys, case, needle):
    grid, line, out = _setup(tmp_path, nodata_at=(3, 4) if case == "nodata" else None)
    argv = [grid, "--line", line, "--out", out, "--zones", "up:0:20,down:20:"]
    if case == "outside":
        (tmp_path / "line.csv").write_text("east_m,north_m\n105,230\n175,205\n")
    if case == "short":
        argv += ["--step-m", "100"]
    if case == "bad_grid":
        text = _read(grid).splitlines()
        text[7] = text[7].rsplit(" ", 1)[0]
        (tmp_path / "dem.asc").write_text("\n".join(text) + "\n")
    if case == "materials":
        (tmp_path / "m.csv").write_text("zone,Kn,Kt,roughness_m,rolling_friction_deg,phi_deg\n"
                                        "up,0.4,0.8,0.5,30,30\n")
        argv += ["--materials", str(tmp_path / "m.csv")]
    rc, _, err = _cli(argv, capsys)
    assert rc == 2
    assert err.count("\n") == 1 and needle in err
    assert err.startswith("python -m terrain.cut: error: ")
    assert not os.path.exists(tmp_path / "out")


def test_old_command_name_still_cuts_and_warns_once(tmp_path):
    """``python -m solvers.profile cut`` (the name before the terrain package) runs
    ``python -m terrain.cut`` for one release: the same files, and one warning line
    on stderr that names the new command."""
    grid, line, out = _setup(tmp_path)
    new = tmp_path / "new.csv"
    args = [grid, "--line", line, "--step-m", "2"]
    old = run_module("solvers.profile", "cut", *args, "--out", out)
    assert old.returncode == 0, old.stderr
    warning = [ln for ln in old.stderr.splitlines() if ln.strip()]
    assert len(warning) == 1 and "deprecated" in warning[0], old.stderr
    assert "'python -m terrain.cut'" in warning[0]
    assert main([*args, "--out", str(new)]) == 0
    assert _read(out) == _read(new)
    bare = run_module("solvers.profile")
    assert bare.returncode == 2 and bare.stderr.count("\n") == 1
    assert "python -m terrain.cut" in bare.stderr


# ---------------------------------------------------------------- the shipped case

SHIPPED = "data/tschamut2014/profile.csv"


def test_shipped_tschamut_profile_loads_and_has_the_stated_zones():
    prof = load_profile(SHIPPED)
    x, z = np.asarray(prof.x_m), np.asarray(prof.z_m)
    assert prof.zone_names == ("steep", "flat")
    names = np.array(prof.segment_zone_names())
    assert x[np.flatnonzero(names == "flat")[0]] == 100.0
    slope = np.degrees(np.arctan(-np.diff(z) / np.diff(x)))
    assert 34 < slope[(x[:-1] >= 45) & (x[:-1] < 90)].mean() < 42       # the ~38 deg slope
    assert abs(slope[(x[:-1] >= 110) & (x[:-1] < 150)].mean()) < 6       # the ~1 deg runout
    _, trace = read_profile_trace(SHIPPED)
    assert len(trace.east_m) == len(x)


def test_recutting_the_shipped_profile_reproduces_it(tmp_path, capsys):
    info = json.loads(_read("data/tschamut2014/profile.cut.json"))
    argv = list(info["argv"])
    out = str(tmp_path / "profile.csv")
    argv[argv.index("--out") + 1] = out
    rc, _, err = _cli(argv, capsys)
    assert rc == 0, err
    for name in ("profile.csv", "profile_materials.csv", "profile.cut.json"):
        new = _read(tmp_path / name)
        old = _read(os.path.join("data/tschamut2014", name))
        if name.endswith(".json"):
            new, old = json.loads(new), json.loads(old)
            for d in (new, old):
                d.pop("argv"), d.pop("command")
        assert new == old, name


def test_non_utf8_line_file_is_one_line_exit_2(tmp_path, capsys):
    """A line CSV saved in Latin-1 is a clear error, not a traceback."""
    grid = tmp_path / "g.asc"
    grid.write_text("ncols 3\nnrows 3\nxllcorner 0\nyllcorner 0\ncellsize 10\n"
                    "NODATA_value -9999\n1 1 1\n1 1 1\n1 1 1\n")
    line = tmp_path / "line.csv"
    line.write_bytes("x,y\n5,5\n25,25\n# caf\xe9\n".encode("latin-1"))
    with pytest.raises(SystemExit) as e:
        main([str(grid), "--line", str(line), "--out", str(tmp_path / "p.csv")])
    err = capsys.readouterr().err
    assert e.value.code == 2 and "UTF-8" in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "p.csv").exists()


def test_geotiff_reads_like_the_ascii_grid(tmp_path):
    """The optional rasterio path (pip install .[geo]): the shipped Tschamut grid
    written as a GeoTIFF reads to the same heights, origin and cell, NODATA
    cells become NaN, and a cut through both gives the same profile."""
    rasterio = pytest.importorskip("rasterio")
    from affine import Affine  # rasterio's own dependency

    asc = read_ascii_grid("data/tschamut2014/terrain_proxy.asc")
    z = asc.z_m[::-1].copy()  # north row first, as a GeoTIFF stores it
    nrows, ncols = z.shape
    west = asc.east0_m - 0.5 * asc.cell_m
    north = asc.north0_m + (nrows - 0.5) * asc.cell_m
    z[0, 0] = -9999.0
    tif = tmp_path / "dem.tif"
    with rasterio.open(tif, "w", driver="GTiff", height=nrows, width=ncols, count=1,
                       dtype="float64",
                       transform=Affine(asc.cell_m, 0.0, west, 0.0, -asc.cell_m, north),
                       nodata=-9999.0) as dst:
        dst.write(z, 1)
    geo = read_raster(str(tif))
    assert np.isnan(geo.z_m[-1, 0])
    same = np.isfinite(geo.z_m)
    np.testing.assert_array_equal(geo.z_m[same], asc.z_m[same])
    assert (geo.cell_m, geo.east0_m, geo.north0_m) == (asc.cell_m, asc.east0_m, asc.north0_m)
    line = read_profile_trace("data/tschamut2014/profile.csv")[1]
    a, b = cut_profile(asc, line, 1.0), cut_profile(geo, line, 1.0)
    np.testing.assert_array_equal(a.z_m, b.z_m)
