"""ISO 2768 tables: exact values, range boundaries, and the cells the standard leaves empty."""

import math

import pytest

from partinspect.tolerances import iso2768
from partinspect.tolerances.iso2768 import (
    GeneralClass,
    NoGeneralTolerance,
    angular_tolerance,
    broken_edge_tolerance,
    circularity_tolerance,
    linear_tolerance,
    parse_general,
    perpendicularity_tolerance,
    runout_tolerance,
    straightness_tolerance,
    symmetry_tolerance,
)


@pytest.mark.parametrize(
    "nominal, cls, expected",
    [
        (0.5, "f", 0.05),  # first range is closed at 0.5
        (3.0, "f", 0.05),
        (10.0, "f", 0.1),
        (6.0, "f", 0.05),  # 6 belongs to "over 3 up to 6"
        (6.001, "f", 0.1),
        (50.0, "f", 0.15),
        (800.0, "f", 0.3),
        (1500.0, "f", 0.5),
        (1.0, "m", 0.1),
        (5.0, "m", 0.1),
        (30.0, "m", 0.2),
        (30.0 + 3e-12, "m", 0.2),  # CAD rounding noise stays in its range
        (50.0, "m", 0.3),
        (120.0, "m", 0.3),
        (200.0, "m", 0.5),
        (500.0, "m", 0.8),
        (1500.0, "m", 1.2),
        (2500.0, "m", 2.0),
        (2.0, "c", 0.2),
        (3.5, "c", 0.3),
        (20.0, "c", 0.5),
        (100.0, "c", 0.8),
        (300.0, "c", 1.2),
        (1000.0, "c", 2.0),
        (1500.0, "c", 3.0),
        (4000.0, "c", 4.0),
        (4.0, "v", 0.5),
        (25.0, "v", 1.0),
        (60.0, "v", 1.5),
        (200.0, "v", 2.5),
        (600.0, "v", 4.0),
        (1200.0, "v", 6.0),
        (3000.0, "v", 8.0),
    ],
)
def test_linear_table(nominal, cls, expected):
    assert linear_tolerance(nominal, cls) == (-expected, expected)


def test_linear_table_is_the_published_one():
    assert iso2768.LINEAR == {
        "f": (0.05, 0.05, 0.1, 0.15, 0.2, 0.3, 0.5, None),
        "m": (0.1, 0.1, 0.2, 0.3, 0.5, 0.8, 1.2, 2.0),
        "c": (0.2, 0.3, 0.5, 0.8, 1.2, 2.0, 3.0, 4.0),
        "v": (None, 0.5, 1.0, 1.5, 2.5, 4.0, 6.0, 8.0),
    }


def test_below_half_a_millimetre_needs_an_explicit_tolerance():
    with pytest.raises(NoGeneralTolerance) as e:
        linear_tolerance(0.4, "m")
    assert str(e.value) == "ISO 2768-1 sets no general tolerance below 0.5 mm; give one in the spec"


@pytest.mark.parametrize("nominal, cls", [(2.0, "v"), (0.5, "v"), (3000.0, "f"), (4000.1, "m"), (-1.0, "m")])
def test_empty_cells_raise(nominal, cls):
    with pytest.raises(NoGeneralTolerance, match="give one in the spec"):
        linear_tolerance(nominal, cls)


def test_v_class_says_which_range_it_lacks():
    with pytest.raises(NoGeneralTolerance, match="class v .* 0.5 up to 3 mm"):
        linear_tolerance(1.0, "v")


def test_nan_is_no_size():
    with pytest.raises(NoGeneralTolerance):
        linear_tolerance(math.nan, "m")


@pytest.mark.parametrize("bad", ["M", "K", "x", None])
def test_unknown_linear_class(bad):
    with pytest.raises(ValueError, match="class must be one of f, m, c, v"):
        linear_tolerance(10.0, bad)


@pytest.mark.parametrize(
    "r, cls, expected",
    [(0.5, "f", 0.2), (3.0, "m", 0.2), (4.0, "m", 0.5), (6.0, "f", 0.5), (8.0, "m", 1.0), (2.0, "c", 0.4), (5.0, "v", 1.0), (100.0, "c", 2.0)],
)
def test_broken_edge_table(r, cls, expected):
    assert broken_edge_tolerance(r, cls) == (-expected, expected)


def test_broken_edge_below_half_a_millimetre():
    with pytest.raises(NoGeneralTolerance, match="below 0.5 mm"):
        broken_edge_tolerance(0.3, "m")


@pytest.mark.parametrize(
    "leg, cls, degrees",
    [
        (5.0, "m", 1.0),
        (10.0, "f", 1.0),
        (10.5, "m", 0.5),
        (50.0, "m", 0.5),
        (100.0, "f", 20 / 60),
        (400.0, "m", 10 / 60),
        (1000.0, "m", 5 / 60),
        (5.0, "c", 1.5),
        (30.0, "c", 1.0),
        (100.0, "c", 0.5),
        (200.0, "c", 15 / 60),
        (500.0, "c", 10 / 60),
        (5.0, "v", 3.0),
        (30.0, "v", 2.0),
        (100.0, "v", 1.0),
        (200.0, "v", 0.5),
        (1000.0, "v", 20 / 60),
    ],
)
def test_angular_table_in_radians(leg, cls, degrees):
    lower, upper = angular_tolerance(leg, cls)
    assert upper == pytest.approx(math.radians(degrees), rel=1e-15)
    assert lower == -upper


@pytest.mark.parametrize(
    "length, cls, expected",
    [
        (5.0, "H", 0.02),
        (10.0, "H", 0.02),
        (20.0, "H", 0.05),
        (50.0, "H", 0.1),
        (200.0, "H", 0.2),
        (500.0, "H", 0.3),
        (2000.0, "H", 0.4),
        (0.1, "K", 0.05),
        (10.0, "K", 0.05),
        (10.1, "K", 0.1),
        (30.0, "K", 0.1),
        (50.0, "K", 0.2),  # K, over 30 up to 100 mm
        (100.0, "K", 0.2),
        (150.0, "K", 0.4),
        (700.0, "K", 0.6),
        (3000.0, "K", 0.8),
        (8.0, "L", 0.1),
        (25.0, "L", 0.2),
        (60.0, "L", 0.4),
        (250.0, "L", 0.8),
        (999.0, "L", 1.2),
        (1001.0, "L", 1.6),
    ],
)
def test_straightness_flatness_table(length, cls, expected):
    assert straightness_tolerance(length, cls) == expected
    assert iso2768.flatness_tolerance(length, cls) == expected


def test_straightness_beyond_3000_mm():
    with pytest.raises(NoGeneralTolerance, match="above 3000 mm"):
        straightness_tolerance(3000.5, "K")


@pytest.mark.parametrize("bad", ["k", "m", "X"])
def test_unknown_geometrical_class(bad):
    with pytest.raises(ValueError, match="class must be one of H, K, L"):
        straightness_tolerance(10.0, bad)


@pytest.mark.parametrize(
    "length, cls, expected",
    [(50.0, "H", 0.2), (100.0, "K", 0.4), (150.0, "K", 0.6), (500.0, "K", 0.8), (2000.0, "K", 1.0), (250.0, "L", 1.0), (800.0, "L", 1.5), (2500.0, "L", 2.0), (2500.0, "H", 0.5)],
)
def test_perpendicularity_table(length, cls, expected):
    assert perpendicularity_tolerance(length, cls) == expected


@pytest.mark.parametrize(
    "length, cls, expected",
    [(50.0, "H", 0.5), (2000.0, "H", 0.5), (50.0, "K", 0.6), (200.0, "K", 0.6), (500.0, "K", 0.8), (1500.0, "K", 1.0), (50.0, "L", 0.6), (200.0, "L", 1.0), (500.0, "L", 1.5), (1500.0, "L", 2.0)],
)
def test_symmetry_table(length, cls, expected):
    assert symmetry_tolerance(length, cls) == expected


def test_runout_table():
    assert [runout_tolerance(c) for c in "HKL"] == [0.1, 0.2, 0.5]


@pytest.mark.parametrize(
    "width, cls, expected",
    [
        (0.4, "K", 0.2),  # diameter 25 under mK: +-0.2 gives 0.4, capped by run-out 0.2
        (0.05, "K", 0.05),  # an individually toleranced diameter: its own width
        (0.2, "K", 0.2),
        (0.6, "L", 0.5),
        (0.3, "H", 0.1),
        (0.08, "H", 0.08),
    ],
)
def test_circularity_is_diameter_tolerance_capped_by_runout(width, cls, expected):
    assert circularity_tolerance(width, cls) == expected


def test_circularity_needs_a_positive_width():
    with pytest.raises(ValueError):
        circularity_tolerance(0.0, "K")


@pytest.mark.parametrize(
    "text, linear, geometrical",
    [
        ("ISO2768-mK", "m", "K"),
        ("ISO 2768-mK", "m", "K"),
        ("mK", "m", "K"),
        ("mk", "m", "K"),
        ("ISO 2768-fH", "f", "H"),
        ("iso 2768 - cL", "c", "L"),
        ("DIN ISO 2768-vL", "v", "L"),
        ("ISO 2768-m", "m", None),
        ("f", "f", None),
    ],
)
def test_parse_general(text, linear, geometrical):
    g = parse_general(text)
    assert g == GeneralClass(linear, geometrical)
    assert g.designation == f"ISO 2768-{linear}{geometrical or ''}"


@pytest.mark.parametrize("text", ["mX", "ISO 2768", "", "xK", "ISO 2768-mKK", "Km", 5, None, "ISO 2769-mK"])
def test_parse_general_rejects(text):
    with pytest.raises(ValueError, match="expected an ISO 2768 class"):
        parse_general(text)


def test_range_labels_use_the_standards_words():
    assert iso2768.range_label(iso2768.LINEAR_RANGES, 0) == "0.5 up to 3 mm"
    assert iso2768.range_label(iso2768.LINEAR_RANGES, 2) == "over 6 up to 30 mm"
    assert iso2768.range_label(iso2768.STRAIGHTNESS_RANGES, 0) == "up to 10 mm"
    assert iso2768.range_label(iso2768.ANGULAR_RANGES, 4) == "over 400 mm"
