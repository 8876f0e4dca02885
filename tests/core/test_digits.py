"""Numbers with the digits their uncertainty allows (orchestrator.core.digits; GUM sec. 7.2.6)."""

import math

import pytest

from orchestrator.core.digits import decimals, rounded, significant, with_uncertainty


@pytest.mark.parametrize("value, uncertainty, text", [
    (2.5091588, 0.2568, "2.51 ± 0.26 kPa"),             # the phantom's landmark pressure with the tension's spread
    (2.5091588, 0.0009166, "2.50916 ± 0.00092 kPa"),    # the parameters' spread alone: the value keeps its digits
    (3.14159, 0.0996, "3.14 ± 0.10 kPa"),               # an uncertainty that rounds up to the next decade
    (1234.5, 560.0, "1230 ± 560 kPa"),                  # places left of the point
    (-0.01234, 0.0031, "-0.0123 ± 0.0031 kPa"),
    (12.0, 0.5, "12.00 ± 0.50 kPa"),
])
def test_value_and_uncertainty_share_the_uncertainty_s_second_significant_place(value, uncertainty, text):
    assert with_uncertainty(value, uncertainty, "kPa") == text


@pytest.mark.parametrize("uncertainty", [None, 0.0, -1.0, math.nan, math.inf])
def test_without_a_usable_uncertainty_a_value_keeps_four_significant_digits(uncertainty):
    assert decimals(uncertainty) is None
    assert rounded(0.0009352417, uncertainty) == "0.0009352"
    assert with_uncertainty(2.5091588, uncertainty, "kPa") == "2.509 kPa"


def test_the_shown_value_is_the_value_to_half_a_unit_of_its_last_place():
    for value, uncertainty in [(2.5091588, 0.2568), (98.765, 4.3), (0.000123456, 0.0000071), (5.0e4, 1234.0)]:
        place = decimals(uncertainty)
        assert abs(float(rounded(value, uncertainty)) - value) <= 0.5 * 10.0 ** -place
        shown = float(rounded(uncertainty, uncertainty))
        assert shown == pytest.approx(float(f"{uncertainty:.2g}"))   # two significant digits of the uncertainty


def test_calfit_pressures_prints_the_whole_spread_with_its_digits():
    from orchestrator.run.stages import pressure_summary

    result = {"landmarks": ["deep_veins"], "mean_kPa": [2.4064037], "std_kPa": [0.0024375776], "cv_percent": [0.1013],
              "central_kPa": [2.4066642], "tension_N_per_mm": 0.16, "tension_rel": 0.1, "plus_kPa": [2.6495072],
              "minus_kPa": [2.1642128]}     # a pressures.json without the spreads: taken from Table 4
    line = pressure_summary(result)[1]
    assert "2.41 ± 0.24" in line and "18.0 ± 1.8" in line        # kPa and mmHg, the tension's spread included
    assert "0.0024" in line and "0.0024375" not in line          # the parameters' share, two significant digits
    assert "+-" not in "\n".join(pressure_summary(result))       # one sign, as the report prints it


@pytest.mark.parametrize("value, text", [
    (3.6, "3.60"), (12.4, "12.4"), (106.0, "106"), (0.9707, "0.971"), (46.14, "46.1"), (-0.04684, "-0.0468"),
    (618.6, "619"), (9.996, "10.0"), (0.0, "0.00"),
    (9.74e-05, "9.74e-05"), (1234567.0, "1.23e+06"),      # exponent notation below 0.001 and from a million up
])
def test_a_number_without_an_uncertainty_keeps_the_significant_digits_a_table_states(value, text):
    assert significant(value, 3) == text
