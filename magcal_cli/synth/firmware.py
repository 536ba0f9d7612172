"""The onboard compass calibration a simulated ArduPilot vehicle flies with (the `.bin` writer applies it).

The simulation itself is physics only (`synth.simulate`); what the firmware does to the field before it logs it
is chosen here and carried by `Simulation.previous` (None: `PreviousCalibration()`, an earlier calibration
with no motor compensation). Per compass: COMPASS_OFS/DIA/ODI/SCALE/MOT with the suffix "", "2", "3"; the
motor compensation type COMPASS_MOTCT (0 off, 1 throttle, 2 current) is global, as in AP_Compass.
"""

from __future__ import annotations

from dataclasses import dataclass, field

Vec3 = tuple[float, float, float]

#: the most compasses ArduPilot calibrates (COMPASS_*, *2, *3) and the reader reads
MAX_COMPASSES = 3


@dataclass(frozen=True)
class CompassParams:
    """One further compass's parameters: COMPASS_OFSn (mG; None: the negated true hard iron missed by a few mG),
    DIAn, ODIn, SCALEn (0: not applied) and MOTn (mG per A with MOTCT=2, mG at full throttle with MOTCT=1)."""

    ofs: Vec3 | None = None
    dia: Vec3 = (1.0, 1.0, 1.0)
    odi: Vec3 = (0.0, 0.0, 0.0)
    scale: float = 0.0
    mot: Vec3 = (0.0, 0.0, 0.0)


#: compasses 2 and 3 of an earlier calibration when `PreviousCalibration.more` does not give them
DEFAULT_MORE = (CompassParams(dia=(0.987, 1.024, 0.979), odi=(-0.012, 0.017, -0.006)),
                CompassParams(dia=(1.015, 0.992, 1.027), odi=(0.008, 0.011, -0.019)))


@dataclass(frozen=True)
class PreviousCalibration:
    """The compass parameters the simulated vehicle flies with; `None` offsets mean 'derived from the truth'.

    The first fields are compass 1's (COMPASS_OFS, DIA, ODI, SCALE, MOT); `more` holds compasses 2 and 3
    (DEFAULT_MORE where not given). `motct` is COMPASS_MOTCT for all of them. `ofs_after` (with
    `change_at_s`) simulates a PARM change of compass 1's offsets during the log, e.g. set from a GCS.
    `current_swing_a` shapes the logged current when the simulation has none (0.8 A plus a 20 s swing).
    `messages` are boot messages logged after the banner (MSG), e.g. a board's unique id. `firmware` is the
    ArduCopter version the vehicle runs (major, minor, patch): its banner, a VER record from 4.0 on (3.x logs have
    none, the reader then reads the version from the banner) and, before 3.6, the motor offsets added before the
    iron matrix instead of after it (`correct_field`).
    """

    ofs: Vec3 | None = None
    dia: Vec3 = (1.031, 0.968, 1.012)
    odi: Vec3 = (0.021, -0.014, 0.009)
    scale: float = 0.0
    mot: Vec3 = (0.0, 0.0, 0.0)
    motct: int = 0
    change_at_s: float | None = None
    ofs_after: Vec3 | None = None
    current_swing_a: float = 0.0
    extra_params: dict[str, float] = field(default_factory=dict)
    more: tuple[CompassParams, ...] = ()
    messages: tuple[str, ...] = ()
    firmware: tuple[int, int, int] = (4, 6, 2)

    @property
    def motor_after_matrix(self) -> bool:
        """Whether this firmware adds the motor offsets after the iron matrix (3.6 and newer)."""
        return self.firmware[:2] >= (3, 6)

    def compass(self, i: int) -> CompassParams:
        """Compass i's parameters (0: the first fields; 1, 2: `more`, else DEFAULT_MORE)."""
        if i == 0:
            return CompassParams(self.ofs, self.dia, self.odi, self.scale, self.mot)
        if not 0 < i < MAX_COMPASSES:
            msg = f"PreviousCalibration: ArduPilot calibrates compasses 0..{MAX_COMPASSES - 1}, not {i}"
            raise ValueError(msg)
        return self.more[i - 1] if i - 1 < len(self.more) else DEFAULT_MORE[i - 1]


#: a stale current-based motor compensation (COMPASS_MOTCT=2): COMPASS_MOT, MOT2, MOT3 in mG per ampere, from a
#: compassmot run before the wiring changed. The simulated field has no current interference, so the firmware
#: subtracts a term that is not there (tens of mG at flight currents) and logs it in MOX..
STALE_CURRENT_COMPENSATION = PreviousCalibration(
    mot=(2.4, -1.6, 3.1), motct=2,
    more=(CompassParams(dia=DEFAULT_MORE[0].dia, odi=DEFAULT_MORE[0].odi, mot=(-1.3, 0.9, 1.8)),
          CompassParams(dia=DEFAULT_MORE[1].dia, odi=DEFAULT_MORE[1].odi, mot=(0.7, 1.2, -0.9))))
