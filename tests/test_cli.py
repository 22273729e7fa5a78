"""The command line: exit codes, one-line errors, fast start."""

import subprocess
import sys

import pytest

from partinspect.cli import main


def run_cli(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "partinspect", *map(str, args)], capture_output=True, text=True, cwd=cwd, timeout=600
    )


def test_help_does_not_import_heavy_libraries():
    code = (
        "import sys\n"
        "from partinspect.cli import main\n"
        "try:\n    main(['--help'])\nexcept SystemExit as e:\n    assert e.code == 0\n"
        "heavy = [m for m in ('cadquery', 'OCP', 'open3d', 'embreex', 'cv2', 'trimesh', 'scipy', 'numpy', 'jinja2') if m in sys.modules]\n"
        "print('HEAVY', heavy, file=sys.stderr)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "HEAVY []" in out.stderr
    assert "inspect PART.step IMAGES_DIR" in out.stdout
    assert "features" in out.stdout and "render" in out.stdout


@pytest.mark.parametrize("sub", ["features", "render", "calibrate", "batch", "spc"])
def test_subcommand_help(sub, capsys):
    with pytest.raises(SystemExit) as e:
        main([sub, "--help"])
    assert e.value.code == 0
    assert f"inspect {sub}" in capsys.readouterr().out


def test_usage_error_is_one_line_exit_2():
    out = run_cli()
    assert out.returncode == 2
    assert out.stderr.count("\n") == 1 and "inspect: error:" in out.stderr
    assert out.stdout == ""


def test_missing_step_file(tmp_path, capsys):
    code = main([str(tmp_path / "nope.step"), str(tmp_path), "-o", str(tmp_path / "out"), "-q"])
    err = capsys.readouterr().err
    assert code == 2
    assert err == f"inspect: error: {tmp_path / 'nope.step'}: STEP file not found\n"
    assert not (tmp_path / "out").exists()


def test_missing_images_folder_named(tmp_path, test_data, capsys):
    step = test_data / "step" / "nist_ftc_11_asme1_rb.stp"
    code = main([str(step), str(tmp_path / "no images"), "-o", str(tmp_path / "out"), "-q"])
    err = capsys.readouterr().err
    assert code == 2
    assert str(tmp_path / "no images") in err and err.count("\n") == 1


def test_output_folder_not_writable(tmp_path, test_data, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    step = test_data / "step" / "nist_ftc_11_asme1_rb.stp"
    code = main([str(step), str(tmp_path), "-o", str(blocker), "-q"])
    assert code == 2
    assert "output path exists and is not a folder" in capsys.readouterr().err


def test_missing_tolerance_file(tmp_path, test_data, capsys):
    step = test_data / "step" / "nist_ftc_11_asme1_rb.stp"
    code = main([str(step), str(tmp_path), "--tolerances", str(tmp_path / "t.yaml"), "-q"])
    assert code == 2
    assert capsys.readouterr().err == f"inspect: error: {tmp_path / 't.yaml'}: tolerance file not found\n"


def test_render_rejects_bad_size(tmp_path, capsys):
    code = main(["render", "part.step", str(tmp_path), "--size", "big"])
    assert code == 2
    assert "--size: expected WIDTHxHEIGHT" in capsys.readouterr().err


def test_features_table_and_json(repo, capsys):
    import json

    step = repo / "examples" / "plate" / "part.step"
    assert main(["features", str(step)]) == 0
    table = capsys.readouterr().out
    assert table.splitlines()[0].split() == ["id", "kind", "geometry", "(part", "frame,", "mm)", "length", "faces"]
    assert table.rstrip().endswith("10 circles, 21 lines")
    assert main(["features", str(step), "--json"]) == 0
    inv = json.loads(capsys.readouterr().out)
    radii = sorted(f["radius"] for f in inv["features"] if f["kind"] == "circle")
    assert radii == [2, 2, 3, 3, 4, 4, 5, 5, 6, 6]


def test_render_then_inspect_an_unseen_step_file(tmp_path, test_data, capsys):
    """The issue's 'done when': render and inspect a real STEP file the project never saw."""
    import json

    step = test_data / "step" / "nist_ftc_11_asme1_rb.stp"
    out = tmp_path / "render"
    assert main(["render", str(step), str(out), "--size", "612x512", "--noise", "1", "--seed", "4", "-q"]) == 0
    assert sorted(p.name for p in (out / "images").iterdir()) == ["calibration.yaml", "left.png", "right.png"]
    truth = json.loads((out / "truth.json").read_text())
    assert truth["image_size"] == [612, 512] or truth.get("images", {}).get("width") == 612
    capsys.readouterr()
    code = main([str(step), str(out / "images"), "-o", str(tmp_path / "inspection"), "-q"])
    # ftc_11 is a washer: seen from any side its circles share one axis, so
    # no pose can be found and the run must say so rather than guess.
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1, err
    assert "ambiguous" in err and "share one axis" in err and str(out / "images") in err
    assert not (tmp_path / "inspection").exists()


def _small_random_rig(path, scale=4):
    """A random rig (:func:`~partinspect.simulate.rig.random_rig`) binned ``scale`` x ``scale``, written to ``path``."""
    from dataclasses import replace

    import numpy as np

    from partinspect.simulate.rig import random_rig
    from partinspect.vision.calibration import write_calibration

    rig = random_rig(11, 100.0)
    K1, K2 = rig.K1.copy(), rig.K2.copy()
    for K in (K1, K2):
        K[:2, :2] /= scale
        K[:2, 2] = (K[:2, 2] + 0.5) / scale - 0.5
    rig = replace(rig, image_size=tuple(int(np.ceil(v / scale)) for v in rig.image_size), K1=K1, K2=K2)
    write_calibration(path, rig)
    return rig


def test_render_through_a_given_rig(repo, tmp_path, capsys):
    """``--rig``: the images are the rig's size, made through it, and calibration.yaml states it."""
    import json

    import cv2
    import numpy as np

    from partinspect.vision.calibration import read_calibration

    rig = _small_random_rig(tmp_path / "rig.yaml")
    step = repo / "examples" / "plate" / "part.step"
    out = tmp_path / "render"
    assert main(["render", str(step), str(out), "--rig", str(tmp_path / "rig.yaml"), "--noise", "1", "-q"]) == 0
    w, h = rig.image_size
    for name in ("left.png", "right.png"):
        assert cv2.imread(str(out / "images" / name), cv2.IMREAD_GRAYSCALE).shape == (h, w)
    assert read_calibration(out / "images" / "calibration.yaml").same_rig(read_calibration(tmp_path / "rig.yaml"))
    truth = json.loads((out / "truth.json").read_text())
    assert truth["image_size"] == [w, h] and truth["distortion"] is True
    # The part is where the rig looks: its box's centre at the rig's fixation point.
    from partinspect.cad.step import load_step
    from partinspect.poses import bounds_of, fixation_point

    P = np.asarray(truth["part_to_camera"], float)
    centre = P[:3, :3] @ bounds_of(load_step(step)).mean(axis=0) + P[:3, 3]
    np.testing.assert_allclose(centre, fixation_point(rig), atol=1e-6)
    left = cv2.imread(str(out / "images" / "left.png"), cv2.IMREAD_GRAYSCALE)
    assert left.std() > 20  # the part is in the image, not only the background


@pytest.mark.parametrize("extra", [["--size", "612x512"], ["--distortion"], ["--defocus", "8,400"]])
def test_render_rig_excludes_what_it_sets(repo, tmp_path, capsys, extra):
    """What a calibration sets, or cannot state (the pixel pitch a defocus needs), is one line and exit 2."""
    _small_random_rig(tmp_path / "rig.yaml")
    step = repo / "examples" / "plate" / "part.step"
    code = main(["render", str(step), str(tmp_path / "r"), "--rig", str(tmp_path / "rig.yaml")] + extra)
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and str(tmp_path / "rig.yaml") in err and extra[0] in err
    if extra[0] == "--defocus":
        assert "--pixel-pitch" in err
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("extra", [["--pixel-pitch", "3.45"], ["--rig", "RIG", "--pixel-pitch", "0"],
                                   ["--rig", "RIG", "--pixel-pitch", "nan"]])
def test_render_pixel_pitch_misused_is_one_line(repo, tmp_path, capsys, extra):
    """A pitch without a rig, or one that is no length, is one line and exit 2."""
    _small_random_rig(tmp_path / "rig.yaml")
    step = repo / "examples" / "plate" / "part.step"
    extra = [str(tmp_path / "rig.yaml") if a == "RIG" else a for a in extra]
    code = main(["render", str(step), str(tmp_path / "r")] + extra)
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "--pixel-pitch" in err
    assert not (tmp_path / "r").exists()


def test_render_defocus_through_a_given_rig(repo, tmp_path):
    """``--defocus`` through ``--rig`` with the sensor's ``--pixel-pitch``: the thin lens is the rig's own lens.

    The test rig is random_rig(11)'s 1920 x 1200 sensor of 5.86 um pixels
    behind a 35 mm lens, binned 4 x 4: 23.44 um pixels.
    """
    import json

    import numpy as np

    from partinspect.poses import fixation_point

    rig = _small_random_rig(tmp_path / "rig.yaml")
    step = repo / "examples" / "plate" / "part.step"
    out = tmp_path / "render"
    focus = float(np.linalg.norm(fixation_point(rig)))
    assert main(["render", str(step), str(out), "--rig", str(tmp_path / "rig.yaml"), "--pixel-pitch", "23.44",
                 "--defocus", f"2.8,{focus:.1f}", "-q"]) == 0
    lens = json.loads((out / "truth.json").read_text())["defocus"]
    assert lens["pixel_pitch"] == pytest.approx(0.02344)
    np.testing.assert_allclose(lens["focal_length"], 35.0, rtol=5e-3)
    # Focused on the part: sharp where it crosses the focus, blurred in front and behind.
    for lo, hi in lens["coc_px"].values():
        assert lo < 0.5 < hi


def test_render_rig_missing_is_one_line(repo, tmp_path, capsys):
    step = repo / "examples" / "plate" / "part.step"
    code = main(["render", str(step), str(tmp_path / "r"), "--rig", str(tmp_path / "none.yaml")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "none.yaml" in err
    assert not (tmp_path / "r").exists()


def test_render_bad_deviation_is_one_line(repo, tmp_path, capsys):
    step = repo / "examples" / "plate" / "part.step"
    code = main(["render", str(step), str(tmp_path / "r"), "--size", "64x64", "--deviate", "circle-99.diameter=0.1"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "circle-99" in err
    assert not (tmp_path / "r").exists()
