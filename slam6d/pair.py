"""Registering one scan against another: the whole of ``slam6d match`` as a library call.

The start comes from the scans' own poses when both files carry one (so odometry is used, as the
method prescribes), else identity; the octree search then widens the basin of convergence before
ICP refines, and when ICP from its winner still fits poorly, the feature-based global search
(:mod:`slam6d.features`, FPFH + RANSAC) proposes a start that does not depend on the first one.
The result keeps every attempt (where ICP started, how it fitted) and which one won, with the
traces of both searches, so a caller can show how the answer was reached.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from slam6d.errors import RegistrationError
from slam6d.features import FeatureConfig, FeatureGuess, feature_guess
from slam6d.geometry import Matrix, invert
from slam6d.icp import ICPConfig, ICPResult, icp
from slam6d.initial_guess import GuessResult, OctreeSearchConfig, octree_guess
from slam6d.scan import Scan

GUESS_CHOICES = ("auto", "octree", "features", "none")
MIN_FITNESS = 0.3  # as the pipeline's default: below it a match from the poses counts as poor


@dataclass
class Attempt:
    """One ICP run of a pair: where its start came from (``start``: the poses; ``octree``; ``features``),
    that start, and how ICP from it ended (fitness and RMS, or the error)."""

    source: str
    start: Matrix
    fitness: float
    rms: float
    error: str = ""


@dataclass
class PairRegistration:
    """``transform`` maps the data scan's points into the model scan's frame (canonical metres).

    ``attempts`` lists every ICP run in order and ``winner`` names the source of the one kept;
    ``guess`` and ``features`` are the octree and feature searches' traces when they ran.
    """

    transform: Matrix
    initial: Matrix
    icp: ICPResult
    guess: GuessResult | None = None
    model_name: str = ""
    data_name: str = ""
    seconds: dict[str, float] = field(default_factory=dict)
    features: FeatureGuess | None = None
    attempts: list[Attempt] = field(default_factory=list)
    winner: str = "start"


Outcome = ICPResult | RegistrationError


def is_poor(outcome: Outcome, min_fitness: float = MIN_FITNESS) -> bool:
    """Whether an ICP outcome calls for the octree search: it failed, or paired too few points."""
    return isinstance(outcome, RegistrationError) or outcome.fitness < min_fitness


def coarse_to_fine(config: ICPConfig, factors: tuple[float, ...] = (4.0, 2.0)) -> ICPConfig:
    """``config`` with first stages at ``factors`` x its max distance (unless it has a schedule).

    For a start that may be further off than the tolerance used between well-predicted scans: a
    loop's drifted start, or a constant-velocity prediction when the motion changed. At the max
    distance alone, ICP from a start a few degrees off in yaw pairs the far points with the wrong
    neighbours and can settle in a wrong basin; a first stage at four times the distance pairs them
    with their own surfaces and costs little once the scans are close.
    """
    if config.distance_schedule:
        return config
    return replace(config, distance_schedule=tuple(f * config.max_distance for f in factors))


FitMeasure = Literal["fitness", "close_fitness"]
"""Which share of an :class:`~slam6d.icp.ICPResult` ranks two fits: paired, or close to the model."""


def better_fit(first: Outcome, second: Outcome, measure: FitMeasure = "close_fitness") -> Outcome:
    """The ICP outcome to keep of two tries at the same scan: a success over a failure, else the
    one scoring higher by ``measure`` (on a tie the first, i.e. the odometry start, stays).

    By default that is the share of the data close to the model (``ICPResult.close_fitness``), not
    the share pairing within the max distance (``fitness``): a wrong basin can pair as many points
    as the right one, only further off their planes. Sequential registration with odometry still
    compares by ``fitness`` (:meth:`slam6d.pipeline.Pipeline._better_fit` says why)."""
    if isinstance(first, RegistrationError):
        return second
    if isinstance(second, RegistrationError) or getattr(second, measure) <= getattr(first, measure):
        return first
    return second


def initial_transform(model: Scan, data: Scan) -> Matrix:
    """Data-to-model start from the scans' poses, identity when either lacks one."""
    if model.has_pose and data.has_pose:
        return invert(model.pose) @ data.pose
    return np.eye(4)


def register_pair(
    model: Scan,
    data: Scan,
    guess: str = "auto",
    icp_config: ICPConfig = ICPConfig(),
    search_config: OctreeSearchConfig | None = None,
    initial: Matrix | None = None,
    min_fitness: float = MIN_FITNESS,
    feature_config: FeatureConfig | None = None,
) -> PairRegistration:
    """ICP from ``initial`` (default: the scans' poses), with the octree or feature search before it.

    ``guess``: ``octree`` always searches near the start first; ``features`` always takes the
    feature-based global guess; ``none`` never searches; ``auto`` searches when the scans carry no
    poses, or when ICP from the poses fails or pairs under ``min_fitness`` of the data, and when ICP
    from the octree winner is poor too, tries the feature guess; it keeps whichever ICP result fits
    best. Searching only when needed matters: the cube-overlap score can prefer co-located scanners
    on range-limited scans, so a good odometry start is worth more than a search.
    """
    if guess not in GUESS_CHOICES:
        raise ValueError(f"guess must be one of {GUESS_CHOICES}, got {guess!r}")
    start = initial_transform(model, data) if initial is None else np.asarray(initial, dtype=np.float64)
    seconds: dict[str, float] = {}
    attempts: list[Attempt] = []
    tried: list[tuple[str, Outcome]] = []

    def attempt(source: str, begin: Matrix) -> Outcome:
        outcome = _icp(model, data, begin, icp_config, seconds)
        tried.append((source, outcome))
        if isinstance(outcome, RegistrationError):
            attempts.append(Attempt(source, begin, 0.0, float("nan"), str(outcome)))
        else:
            attempts.append(Attempt(source, begin, outcome.fitness, outcome.rms))
        return outcome

    octree: GuessResult | None = None
    features: FeatureGuess | None = None
    if guess == "features":
        features = _features(model, data, feature_config, seconds)
        outcome = attempt("features", features.transform)
    else:
        search_first = guess == "octree" or (
            guess == "auto" and initial is None and not (model.has_pose and data.has_pose)
        )
        if search_first:
            octree = _search(model, data, start, search_config, seconds)
            outcome = attempt("octree", octree.transform)
        else:
            outcome = attempt("start", start)
        if guess == "auto" and octree is None and is_poor(outcome, min_fitness):
            octree = _search(model, data, start, search_config, seconds)
            outcome = better_fit(outcome, attempt("octree", octree.transform))
        if guess == "auto" and is_poor(outcome, min_fitness):
            features = _features(model, data, feature_config, seconds)
            outcome = better_fit(outcome, attempt("features", features.transform))
    if isinstance(outcome, RegistrationError):
        raise RegistrationError(f"{data.name} onto {model.name}: {outcome}") from outcome
    return PairRegistration(
        outcome.transform,
        start,
        outcome,
        octree,
        model.name,
        data.name,
        seconds,
        features=features,
        attempts=attempts,
        winner=next(source for source, kept in tried if kept is outcome),
    )


def _features(model: Scan, data: Scan, config: FeatureConfig | None, seconds: dict[str, float]) -> FeatureGuess:
    began = time.perf_counter()
    result = feature_guess(model.points, data.points, config)
    seconds["feature_guess"] = seconds.get("feature_guess", 0.0) + time.perf_counter() - began
    return result


def _search(
    model: Scan, data: Scan, start: Matrix, config: OctreeSearchConfig | None, seconds: dict[str, float]
) -> GuessResult:
    began = time.perf_counter()
    result = octree_guess(model.points, data.points, start, config)
    seconds["octree_guess"] = seconds.get("octree_guess", 0.0) + time.perf_counter() - began
    return result


def _icp(model: Scan, data: Scan, start: Matrix, config: ICPConfig, seconds: dict[str, float]) -> Outcome:
    began = time.perf_counter()
    try:
        return icp(model.points, data.points, start, config)
    except RegistrationError as exc:
        return exc
    finally:
        seconds["icp"] = seconds.get("icp", 0.0) + time.perf_counter() - began
