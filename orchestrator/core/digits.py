"""Numbers shown with the digits their uncertainty allows.

A value is printed to the decimal place of its uncertainty's second significant digit, and the uncertainty with
two significant digits (JCGM 100:2008, the GUM, sec. 7.2.6: "it usually suffices to quote u_c and U to at most two
significant digits", and the estimate rounded to be consistent with them). A pressure of 2.509159 kPa known to
0.2568 kPa reads 2.51 ± 0.26 kPa, not 2.509 ± 0.0009166. Without a usable uncertainty (none, zero, not finite)
a value keeps FALLBACK_SIGNIFICANT significant digits (`rounded`), or the significance a table states (`significant`:
the run report's tables give a number that has no uncertainty three significant digits). The sign between a value
and its uncertainty is PLUS_MINUS, "±", the report's, the figures' and the terminal's alike.
"""

from __future__ import annotations

import math

UNCERTAINTY_SIGNIFICANT = 2
FALLBACK_SIGNIFICANT = 4
PLUS_MINUS = "\u00b1"      # ±


def decimals(uncertainty: float | None) -> int | None:
    """The decimal place (digits after the point; negative: tens, hundreds...) of the uncertainty's last
    significant digit, or None when the uncertainty cannot set one."""
    if uncertainty is None or not math.isfinite(uncertainty) or uncertainty <= 0.0:
        return None
    exponent = math.floor(math.log10(uncertainty))
    place = UNCERTAINTY_SIGNIFICANT - 1 - exponent
    if round(uncertainty, place) >= 10.0 ** (exponent + 1):     # 0.0996 rounds up to 0.10: one place fewer
        place -= 1
    return place


def interval_uncertainty(low: float, high: float) -> float:
    """The standard uncertainty a 95 % interval implies for the digits of its numbers: its width over 4 (it spans
    about 4 standard deviations of a normal estimate)."""
    return abs(high - low) / 4.0


def rounded(value: float, uncertainty: float | None) -> str:
    """The value as text, to the place its uncertainty allows (module text)."""
    if not math.isfinite(value):
        return str(value)
    place = decimals(uncertainty)
    if place is None:
        return f"{value:.{FALLBACK_SIGNIFICANT}g}"
    if place <= 0:
        return f"{round(value, place):.0f}"
    return f"{value:.{place}f}"


def significant(value: float, digits: int) -> str:
    """The value with `digits` significant digits, trailing zeros kept (3.60, 12.4, 106, 0.0235); in exponent
    notation below 0.001 or from a million up (9.81e-05)."""
    if not math.isfinite(value):
        return str(value)
    if value == 0.0:
        return f"{0.0:.{digits - 1}f}"
    exponent = math.floor(math.log10(abs(value)))
    if round(abs(value), digits - 1 - exponent) >= 10.0 ** (exponent + 1):    # 9.996 to 3 digits: 10.0
        exponent += 1
    if exponent < -3 or exponent >= 6:
        return f"{value:.{digits - 1}e}"
    place = digits - 1 - exponent
    return f"{value:.{place}f}" if place > 0 else f"{round(value, place):.0f}"


def with_uncertainty(value: float, uncertainty: float | None, unit: str = "") -> str:
    """'value ± uncertainty unit', both to the uncertainty's place (module text)."""
    text = rounded(value, uncertainty)
    if decimals(uncertainty) is not None:
        text += f" {PLUS_MINUS} {rounded(uncertainty, uncertainty)}"
    return f"{text} {unit}".rstrip()
