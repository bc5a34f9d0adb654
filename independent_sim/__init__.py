"""Independent simulator of hidden-effect calibration data in PAINT's layout (shares no code with heliojax).

Public: `generate(effect, out_dir, seed, ...) -> truth dict`, `EFFECTS` (name -> spec).
"""

from ._effects import EFFECTS as EFFECTS
from ._generate import generate as generate
