"""``calib.files.provenance``: the command a run records is the one that repeats
it, whether the command ran from a shell or was called with its arguments
inside another program (a notebook, a study script, a test)."""

from __future__ import annotations

import sys

from calib.files.provenance import command_args, command_line, provenance


def test_a_command_called_in_process_records_its_own_arguments(monkeypatch, tmp_path):
    data = tmp_path / "my data.csv"
    data.write_text("x\n")
    monkeypatch.setattr(sys, "argv", ["scripts/study.py", "fit", "--groups", "8", "--", "d.csv"])
    # outside a command's main (a library call): none of the process's arguments
    assert command_line("notebooks/05_protection.py") == "notebooks/05_protection.py"
    with command_args([str(data), "--seed", 3]):
        rec = provenance("python -m calib.fit", 3, {"data": str(data)})
        assert rec["command"] == f"python -m calib.fit '{data}' --seed 3"
        # an explicit argv (a check run inside the command) still wins
        assert command_line("python -m calib.validate", ["a.json"]) == (
            "python -m calib.validate a.json")
        with command_args(None):  # a command's main() called without arguments
            assert command_line("python -m calib.fit").endswith("fit --groups 8 -- d.csv")
    assert command_line("python -m calib.fit", []) == "python -m calib.fit"
    with command_args(None):  # main() from a shell: the process's arguments
        assert command_line("python -m calib.synth") == ("python -m calib.synth fit "
                                                         "--groups 8 -- d.csv")


def test_a_command_main_is_running_a_library_call_is_not(monkeypatch):
    from calib.files.provenance import command_running

    monkeypatch.setattr(sys, "argv", ["/usr/bin/ipykernel", "-f", "kernel.json"])
    assert not command_running()
    with command_args(None):  # main() from a shell: the process's arguments
        assert command_running()
        assert command_line("python -m calib.fit") == "python -m calib.fit -f kernel.json"
    assert not command_running()


def test_a_library_fit_records_the_command_that_repeats_it():
    """``run_fit`` called from a notebook records ``python -m calib.fit`` with its
    own options (``fit_argv``), which the command parses back into the same
    call (``run_options``), every keyword of ``run_fit`` but the two that only
    show progress."""
    import inspect

    from calib.fit import build_parser, fit_argv, run_fit, run_options

    keywords = set(inspect.signature(run_fit).parameters) - {"progress", "report"}
    assert set(inspect.signature(fit_argv).parameters) == keywords
    default = {k: p.default for k, p in inspect.signature(run_fit).parameters.items()
               if k in keywords}
    calls = [dict(default, data="d.csv", out="o"),
             dict(data="my data.csv", out="res/x", profile="p.csv", models=("crsp",),
                  methods=("bayes",), rolling_resistance="zones",
                  effects=("fragmentation", "vegetation_belt"), alpha_law="constant",
                  seed=7, quick=True, holdout_fraction=0.3, release_tolerance_m=0.25,
                  velocities="v.csv", dem_max_time_s=None,  # CRSP alone: no DEM time
                  row_shapes=True),
             dict(default, data="d.csv", out="o", models=("dem",), methods=("gradient",)),
             dict(default, data="d.csv", out="o", models=("dem",), dem_max_time_s=175.0)]
    for call in calls:
        argv = fit_argv(**call)
        assert run_options(build_parser().parse_args(argv)) == call, argv
