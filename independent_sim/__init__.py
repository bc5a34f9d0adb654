"""Independent simulator of hidden-effect calibration data in PAINT's layout (shares no code with heliojax).

Public: `generate(effect, out_dir, seed, ...) -> truth dict`, `EFFECTS` (name -> spec), `NOISE_KINDS` (the
camera noise's laws `generate` offers), `plant_mount(suite_dir,
heliostat)` (the true plant of a written suite) and `reflect`.
"""

from ._effects import EFFECTS as EFFECTS
from ._generate import NOISE_KINDS as NOISE_KINDS, generate as generate, plant_mount as plant_mount
from ._mount import reflect as reflect
