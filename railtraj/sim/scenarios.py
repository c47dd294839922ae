"""The scenario catalogue: named, frozen descriptions of a survey to simulate.

A :class:`Scenario` is plain data (tunnel geometry, runs, scanner, error model) so it can be
printed, hashed, stored as JSON next to the truth and compared. :meth:`Scenario.scaled` shrinks
or grows it (lengths and point density) for quick tests and big benchmarks. ``mixed`` is the
built-in demo.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

from railtraj.errors import ConfigError
from railtraj.sim.drift import DriftSpec, Multipath
from railtraj.sim.geometry import GeometrySpec
from railtraj.sim.runs import RunSpec
from railtraj.sim.scanner import ScannerSpec
from railtraj.sim.track import Alignment

MIN_SECTION = 12.0       #: no section shrinks below this many metres
MIN_POINTS = 120         #: nor a profile below this many points


@dataclass(frozen=True)
class Scenario:
    """Everything needed to simulate one survey (the seed is given separately)."""

    name: str
    description: str
    geometry: GeometrySpec
    runs: tuple[RunSpec, ...]
    scanner: ScannerSpec = field(default_factory=ScannerSpec)
    drift: DriftSpec = field(default_factory=DriftSpec)
    rate_hz: float = 200.0
    tile_size: float = 25.0
    crs: str = "EPSG:7405"
    size: float = 1.0

    def scaled(self, size: float) -> Scenario:
        """Lengths (sections, curves, sparse-object spacings) times ``size``, points per profile
        times ``sqrt(size)`` (so that small surveys still resolve surfaces across the profile);
        repeated structure (ribs, sleepers, pillars) keeps its spacing."""
        if not size > 0:
            raise ConfigError(f"size must be a positive number (1.0 = full size), got {size}")
        if size == 1.0:
            return self
        g = self.geometry

        def sp(x: float | None) -> float | None:
            return None if not x else x * size

        geometry = replace(
            g, sections=tuple((k, max(MIN_SECTION, n * size)) for k, n in g.sections),
            alignment=g.alignment.scaled(size), niche_spacing=sp(g.niche_spacing),
            box_spacing=sp(g.box_spacing), tray_length=sp(g.tray_length),
            mast_spacing=sp(g.mast_spacing), control_spacing=sp(g.control_spacing))
        scanner = replace(self.scanner, points_per_profile=max(
            MIN_POINTS, int(round(self.scanner.points_per_profile * size ** 0.5))))
        drift = replace(self.drift, multipath=tuple(
            replace(m, ramp=max(5.0, m.ramp * size)) for m in self.drift.multipath))
        return replace(self, geometry=geometry, scanner=scanner, drift=drift, size=self.size * size)

    def to_dict(self) -> dict:
        """JSON-ready parameters (stored in the truth folder)."""
        return asdict(self)


def _thesis() -> Scenario:
    return Scenario(
        "thesis", "straight single-track tunnel with arch ribs every 1.5 m, 2 opposite runs",
        GeometrySpec(sections=(("cutting", 40.0), ("rect", 300.0), ("cutting", 40.0)),
                     alignment=Alignment(grades=((1e9, 0.003),)), tracks=1),
        (RunSpec("run_a", direction=1, speed=10.0, start_time=300000.0),
         RunSpec("run_b", direction=-1, speed=11.0, start_time=300600.0)))


def _mixed() -> Scenario:
    return Scenario(
        "mixed", "the demo: 600 m of twin-track tunnel (ribbed, station, circular, ribbed) between "
        "open cuttings, on a curve and a grade; 3 runs, one on the other track",
        GeometrySpec(
            sections=(("cutting", 70.0), ("rect", 180.0), ("station", 90.0), ("circular", 170.0),
                      ("rect", 160.0), ("cutting", 70.0)),
            alignment=Alignment(origin=(530000.0, 180010.0, 10.0), heading_deg=75.0,
                                curves=((160.0, 0.0), (260.0, 550.0), (1e9, 0.0)),
                                grades=((350.0, 0.004), (1e9, -0.0025))),
            tracks=2),
        (RunSpec("run_a", track=0, direction=1, speed=11.0, start_time=300000.0),
         RunSpec("run_b", track=0, direction=-1, speed=13.0, start_time=300900.0),
         RunSpec("run_c", track=1, direction=1, speed=11.0, start_time=301800.0)),
        scanner=ScannerSpec(points_per_profile=600))


def _portal_trap() -> Scenario:
    base = _thesis()
    return replace(
        base, name="portal_trap",
        description="ribbed tunnel; run_a gets a GNSS multipath bias at its entry portal that "
        "its reported sd does not show, run_b a small heading bias; 3 runs",
        geometry=replace(base.geometry, sections=(("cutting", 60.0), ("rect", 320.0), ("cutting", 60.0))),
        runs=(*base.runs, RunSpec("run_c", direction=1, speed=9.0, start_time=301200.0)),
        drift=DriftSpec(multipath=(Multipath("run_a", portal=0, bias=(0.3, -0.25, 0.1)),),
                        heading_bias_deg=0.03, heading_bias_runs=("run_b",)))


def _control() -> Scenario:
    return Scenario(
        "control", "twin-track tunnel with survey targets every ~50 m and control.csv; 2 runs",
        GeometrySpec(sections=(("cutting", 40.0), ("rect", 200.0), ("circular", 150.0), ("cutting", 40.0)),
                     alignment=Alignment(curves=((150.0, 0.0), (1e9, -800.0))), tracks=2,
                     control_spacing=50.0),
        (RunSpec("run_a", track=0, direction=1, speed=10.0, start_time=300000.0),
         RunSpec("run_b", track=1, direction=-1, speed=10.0, start_time=300600.0)))


def _feature_poor() -> Scenario:
    return Scenario(
        "feature_poor", "smooth circular single-track tunnel on slab track, a continuous cable "
        "tray and a cabinet every ~200 m: the hardest case; 2 opposite runs",
        GeometrySpec(sections=(("cutting", 40.0), ("circular", 400.0), ("cutting", 40.0)),
                     tracks=1, box_spacing=200.0, tray_length=1e6, niche_spacing=0.0),
        (RunSpec("run_a", direction=1, speed=10.0, start_time=300000.0),
         RunSpec("run_b", direction=-1, speed=10.0, start_time=300600.0)))


def _commensurate() -> Scenario:
    return Scenario(
        "commensurate", "straight ribbed tunnel whose ribs (1.5 m) and sleepers (0.6 m, a standard "
        "spacing) repeat together every 3.0 m, niches and boxes 20-40 m apart; 2 opposite runs",
        GeometrySpec(sections=(("cutting", 40.0), ("rect", 300.0), ("cutting", 40.0)),
                     alignment=Alignment(grades=((1e9, 0.003),)), tracks=1, sleeper_spacing=0.6,
                     niche_spacing=60.0, box_spacing=45.0, layout_seed=11),
        (RunSpec("run_a", direction=1, speed=10.0, start_time=300000.0),
         RunSpec("run_b", direction=-1, speed=12.0, start_time=300600.0)))


def _commensurate_fast() -> Scenario:
    base = _commensurate()
    return replace(
        base, name="commensurate_fast",
        description="the commensurate tunnel driven at 18 and 20 m/s by a sparser scanner (125 profiles/s: "
        "profiles 15 cm apart, 350 points each)",
        runs=(RunSpec("run_a", direction=1, speed=18.0, start_time=300000.0),
              RunSpec("run_b", direction=-1, speed=20.0, start_time=300600.0)),
        scanner=ScannerSpec(profile_rate=125.0, points_per_profile=350))


def _commensurate_speeds() -> Scenario:
    base = _commensurate()
    return replace(
        base, name="commensurate_speeds",
        description="the commensurate tunnel driven at 5 and 20 m/s: run a's profiles 2 cm apart, run b's 8 cm",
        runs=(RunSpec("run_a", direction=1, speed=5.0, start_time=300000.0),
              RunSpec("run_b", direction=-1, speed=20.0, start_time=300600.0)))


def _tube() -> Scenario:
    return Scenario(
        "tube", "segmental-lining bored tube on slab track: ring joints every 1.25 m and 100+ m "
        "without another feature (a cabinet every ~150 m); 2 opposite runs",
        GeometrySpec(sections=(("cutting", 40.0), ("circular", 450.0), ("cutting", 40.0)), tracks=1,
                     ring_spacing=1.25, box_spacing=150.0, tray_length=0.0, niche_spacing=0.0, layout_seed=5),
        (RunSpec("run_a", direction=1, speed=12.0, start_time=300000.0),
         RunSpec("run_b", direction=-1, speed=10.0, start_time=300600.0)))


CATALOGUE = {s.name: s for s in (_thesis(), _mixed(), _portal_trap(), _control(), _feature_poor(),
                                 _commensurate(), _commensurate_fast(), _commensurate_speeds(), _tube())}
DEMO = "mixed"


def get_scenario(scenario: str | Scenario, size: float = 1.0) -> Scenario:
    """A catalogue scenario by name (or a Scenario as is), scaled by ``size``."""
    if isinstance(scenario, Scenario):
        return scenario.scaled(size)
    if scenario not in CATALOGUE:
        raise ConfigError(f"unknown scenario {scenario!r}; choose from {', '.join(CATALOGUE)}")
    return CATALOGUE[scenario].scaled(size)
