"""Units: the engine's decks are in MPa, mm and N; calfit's parameters in kPa; the pressures a user reads in kPa
and mmHg."""

from __future__ import annotations

KPA_PER_MPA = 1e3
MMHG_PER_KPA = 7.50062    # 1 mmHg = 133.322 Pa
