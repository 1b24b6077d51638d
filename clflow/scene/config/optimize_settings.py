"""The scene config's ``optimize`` section: the optimiser, its global search and time budget,
each field declaring its key (``keys.setting``)."""

from __future__ import annotations

from dataclasses import dataclass

from clflow.materials import Param
from clflow.scene.config.keys import MAX_GRID, MAX_RATE, setting

VELOCITY = "velocity"  # the name of the object's initial velocity in optimize.parameters, evaluation.ground_truth
VELOCITY_COMPONENTS = ("velocity_x", "velocity_y", "velocity_z")  # its components: m/s, scene axes
#: the guidance video's clock, the scene's own parameter (no OBJECT. with several objects): the
#: seconds of motion one second of the video shows. A generated video's clock is not the
#: simulation's (a model asked for 8 fps may move at 0.7x or 1.3x): the simulated frame interval
#: is time_scale / simulation.fps, 1 the video's stated rate, below 1 slow motion
TIME_SCALE = Param(
    "time_scale", "tau", "1", 1.0, (0.1, 10.0), (0.5, 2.0),
    doc="seconds of the scene's motion one second of the guidance video shows",
)  # fmt: skip
MAX_HYPOTHESES = 16  # material combinations optimize.material may make (each a search of its own)

OPTIMIZERS = ("adam", "levenberg_marquardt")


@dataclass(frozen=True)
class SearchSettings:
    """The global phase before the gradient iterations (clflow.pipeline.fit.search)."""

    samples: int = setting(
        32, kind="integer", low=1, doc="forward-only runs over the parameter box, the start included"
    )
    decades: float = setting(
        3.0,
        kind="number",
        low=0.0,
        strict_low=True,
        doc="the box of a log-scale parameter is its start times 10^(+-decades), within its typical range",
    )
    frames: int = setting(0, kind="integer", low=0, doc="frames in the search's loss; 0 means all frames")
    starts: int = setting(
        1,
        kind="integer",
        low=1,
        doc="at most `samples`: the best samples each polished by `start_iterations` Levenberg-Marquardt "
        "iterations, the run going on from the best of them; more than 1 needs `method: levenberg_marquardt`; "
        "each start but the kept one adds `start_iterations` to `iterations`",
    )
    start_iterations: int = setting(
        3,
        kind="integer",
        low=1,
        doc="Levenberg-Marquardt iterations per start before the starts are compared",
    )
    refine: int = setting(
        0,
        kind="integer",
        low=0,
        doc="a second round of this many samples after the design, shared among the neighbourhoods of the best "
        "`starts` samples that lie outside each other's (a neighbourhood spans one design spacing, the box's "
        "width / samples^(1/parameters), per parameter); each neighbourhood's best sample is then a start. 0: "
        "no second round",
    )
    object_samples: int = setting(
        12,
        kind="integer",
        low=0,
        doc="with material parameters of two objects or more, a round per object after the design (before the "
        "second round): this many samples per parameter of the object over its own part of the box, every other "
        'parameter held at the best sample so far (docs/pipeline.md, "A round per object"). 0: none; a config '
        "of one object has none",
    )
    grid_resolution: int = setting(
        0,
        kind="integer",
        low=0,
        doc="0 or at least 11, at most `simulation.grid_resolution`: the search and the starts' polish run on a "
        "grid of this many nodes along the domain's longest side (its own particle fill), the main phase on "
        "`simulation.grid_resolution`; the polished starts are compared on the main grid. 0: the simulation's "
        "grid throughout. A coarse search grid makes the global phase cheap where the main phase needs a fine "
        "one (docs/pipeline.md)",
    )


@dataclass(frozen=True)
class BudgetSettings:
    """``optimize.budget``: the run's wall time, which chooses the main phase's grid from the
    device's measured speed (clflow.pipeline.fit.budget)."""

    seconds: float = setting(  # the whole optimisation: search, polishes, iterations, diagnostics
        kind="number",
        unit="s",
        low=0.0,
        strict_low=True,
        doc="the optimisation's wall time (`clflow optimize --budget` sets it). The main phase's grid becomes "
        "the finest candidate, from the search's grid up, whose predicted run fits: each is timed on this device "
        'at the starting parameters (docs/pipeline.md, "A time budget"). Absent `budget`: '
        "`simulation.grid_resolution`",
    )
    max_grid_resolution: int = setting(
        0,
        kind="integer",
        low=0,
        high=MAX_GRID,
        doc="0 or from the search's grid up: the finest main grid to consider; 0: twice "
        "`simulation.grid_resolution` in cells",
    )


@dataclass(frozen=True)
class OptimizeSettings:
    parameters: tuple[str, ...] = setting(
        (),
        kind="list",
        doc="a list of the material's parameter names, `density` or `velocity` (several objects: `OBJECT.PARAM`, "
        "see `objects`), and `time_scale`, the video's clock (the scene's, never OBJECT.time_scale; "
        'docs/pipeline.md, "An unknown playback speed"); `clflow optimize` needs at least one *(run)*',
    )
    learning_rates: dict[str, float] = setting(  # in the optimiser's space
        factory=dict,
        kind="mapping",
        low=0.0,
        strict_low=True,
        high=MAX_RATE,
        shown="`0.1` each",
        doc="a mapping from a name in `parameters` (or `velocity`, `OBJECT.velocity` of an object it estimates, "
        "with `estimate_velocity`) to a rate",
    )
    iterations: int = setting(
        30, kind="integer", low=1, doc="the main phase's iterations (`clflow optimize --iterations` overrides it)"
    )
    horizon_start: int = setting(
        0,
        kind="integer",
        key="horizon.start",
        low=0,
        doc="frames in the first iteration's loss; 0 means all frames",
    )
    horizon_step: int = setting(0, kind="integer", key="horizon.step", low=0, doc="frames added per iteration")
    final_rate: float = setting(
        0.1,
        kind="number",
        low=0.0,
        high=1.0,
        doc="the rates fall (cosine) to this fraction of themselves by the last iteration",
    )
    search: SearchSettings | None = setting(  # None: no global phase
        None,
        kind="section",
        doc="the global phase: before the gradient iterations, forward-only runs at the start and at a scrambled "
        "Sobol design of the parameter box; the iterations start from the best. Absent: no search",
    )
    method: str = setting(
        "adam",
        kind="choice",
        choices=OPTIMIZERS,
        doc="`adam` (log-space Adam with adaptive restart, learning rates and horizon as above) or "
        "`levenberg_marquardt` (damped Gauss-Newton on the flow residuals, Jacobian by finite differences: one "
        "forward run per parameter and iteration, no learning rates; needs `flow.loss: l2`)",
    )
    bounds: dict[str, tuple[float, float]] = setting(  # SI; the search box of a parameter
        factory=dict,
        kind="mapping",
        shown="none",
        doc="a mapping from a name in `parameters` to `[lower, upper]` (SI, lower < upper, within the parameter's "
        "valid range): that parameter's search box instead of the default (a bounded parameter's default box is "
        "its typical range, widened to hold the start); the start must lie inside",
    )
    # material hypotheses: object name -> registry names; each combination is searched before
    # the one that fits best is optimised (clflow.pipeline.hypotheses); {} for the config's own
    materials: dict[str, tuple[str, ...]] = setting(
        factory=dict,
        kind="list",
        key="material",
        shown="none",
        doc="a list of material names (hypotheses, e.g. `[elastic, plasticine]`): each runs the search alone over "
        "its entries of `parameters` (each hypothesis needs at least one; every parameter belongs to at least "
        "one), the one whose best sample has the lowest loss is optimised; turns the search on with its defaults "
        "when `search` is absent (see below). With several objects a mapping from object names to such lists "
        "(`{jelly: [elastic, plasticine], heap: [sand, snow]}`; each list against its object's `OBJECT.PARAM` "
        f"entries, the objects not named keep their material): the hypotheses are every combination, at most "
        f"{MAX_HYPOTHESES}",
    )
    estimate_velocity_frames: int = setting(  # frames in the loss of the velocity phase
        0,
        kind="integer",
        key="estimate_velocity.frames",
        low=1,
        required=True,
        doc="at most `simulation.frames`: frames in the velocity phase's loss",
    )
    estimate_velocity_iterations: int = setting(  # before the main phase (0: none)
        0,
        kind="integer",
        key="estimate_velocity.iterations",
        low=1,
        required=True,
        doc="iterations of the velocity phase; give both keys, or leave out `estimate_velocity` for no velocity phase",
    )
    # the objects whose velocities the velocity phase estimates, by name (of one object: its one)
    estimate_velocity_objects: tuple[str, ...] = setting(
        (),
        kind="list",
        key="estimate_velocity.objects",
        required=True,
        shown="",
        doc="several objects only, and then required: the names of the objects whose initial velocities the "
        "phase estimates (each its `OBJECT.velocity`, rate `learning_rates.OBJECT.velocity`); the others keep "
        "theirs. An object at rest has nothing to estimate, and Adam's steps (about the rate each, whatever the "
        "gradient) would move its weakly observed components",
    )
    prior: str = setting(
        "none",
        kind="choice",
        choices=("none", "knowledge"),
        doc="`knowledge`: after the fit, a parameter the video leaves unresolved takes the material knowledge base's "
        "value for the object (the query's answer, else the median of its type's entries), and a weakly constrained "
        "one outside the knowledge base's range for it moves into that range; each within its own 90 % range, the "
        "others refitted, kept only within the fit's loss tolerance; the ranges stay the video's, and "
        "`metrics.json`'s `prior` says who decided each parameter (docs/pipeline.md, \"A prior from the material "
        'query")',
    )
    budget: BudgetSettings | None = setting(  # None: the main phase runs on simulation.grid_resolution
        None,
        kind="section",
        doc="a wall-time budget that chooses the main phase's grid (default: none; docs/pipeline.md)",
    )

    def parameters_by_object(self) -> dict[str, tuple[str, ...]]:
        """Object name -> its optimised material parameters (OBJECT.PARAM), in the config's
        order, where they belong to two objects or more; else {} (the search's object rounds)."""
        names = [n for n in self.parameters if n != TIME_SCALE.name]  # the scene's, no object's
        if not all("." in name for name in names):
            return {}
        groups: dict[str, tuple[str, ...]] = {}
        for name in names:
            obj, _, param = name.partition(".")
            if param != VELOCITY:  # the search looks at material parameters only
                groups[obj] = groups.get(obj, ()) + (name,)
        return groups if len(groups) > 1 else {}

    def object_round_samples(self) -> int:
        """The samples of the search's object rounds, all objects together (0: none)."""
        if self.search is None:
            return 0
        return self.search.object_samples * sum(map(len, self.parameters_by_object().values()))


__all__ = [
    "BudgetSettings",
    "MAX_HYPOTHESES",
    "OPTIMIZERS",
    "OptimizeSettings",
    "SearchSettings",
    "TIME_SCALE",
    "VELOCITY",
    "VELOCITY_COMPONENTS",
]
