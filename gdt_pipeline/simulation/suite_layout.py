"""Random layouts of the scene suite: which parts stand where on the floor plate (non-overlapping footprints), and
what changed between the CAD (E0) and the as-is scene (E1): parts added, removed and moved.

Sizes scale with the scene's side ``L`` (itself scaled to the stations' range), except the pipes' and cylinders'
diameters (3–15 cm, at most an eighth of ``L``) and the thin dimensions of plates, brackets and rails."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .suite_shapes import box, channel_rail, cylinder, floor_plate, footprint, l_bracket, placed, rectangles_overlap

KINDS = ("cabinet", "pipe", "cylinder", "plate", "panel", "bracket", "rail")
KIND_WEIGHTS = (0.2, 0.2, 0.15, 0.1, 0.1, 0.15, 0.1)
CLEARANCE = 0.03  # × L: gap kept between parts, so a moved part has room and no two parts touch
HALF_AREA = 0.46  # × L: parts stay within this half side (the floor plate's half side is 0.5 L)
LARGE_MOVE = (0.1, 0.3)  # × L: the range of a "large" move
LARGE_MOVE_SHARE = 0.3  # share of moves drawn large; the others are 1–10 × the move scale


@dataclass
class Part:
    """One part of the scene: its shape in its own frame, where it stands and its mesh there."""

    name: str
    kind: str
    shape: object  # trimesh.Trimesh in its own frame
    yaw: float
    xy: np.ndarray
    mesh: object = field(init=False)
    rect: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.mesh = placed(self.shape, self.yaw, (float(self.xy[0]), float(self.xy[1])))
        self.rect = footprint(self.mesh)

    def moved_to(self, xy: np.ndarray) -> Part:
        """The same part standing at ``xy``."""
        return Part(self.name, self.kind, self.shape, self.yaw, np.asarray(xy, dtype=np.float64))


@dataclass
class Layout:
    """The CAD parts (E0), the as-is parts (E1) and what happened to each."""

    side: float
    floor: object  # trimesh.Trimesh
    cad: dict[str, Part]
    asis: dict[str, Part]
    states: dict[str, str]
    displacements: dict[str, list[float]]


def _diameter(rng: np.random.Generator, L: float) -> float:
    return float(rng.uniform(0.03, max(0.031, min(0.15, L / 8))))


def draw_shape(kind: str, rng: np.random.Generator, L: float):  # -> trimesh.Trimesh
    """A random part of ``kind`` for a scene of side ``L`` (metres), in its own frame."""
    u = rng.uniform
    if kind == "cabinet":
        return box((u(0.08, 0.22) * L, u(0.08, 0.18) * L, u(0.10, 0.35) * L))
    if kind == "pipe":
        return cylinder(_diameter(rng, L), u(0.25, 0.55) * L, lying=True)
    if kind == "cylinder":
        return cylinder(_diameter(rng, L), u(0.08, 0.4) * L, lying=False)
    if kind == "plate":
        return box((u(0.12, 0.3) * L, u(0.10, 0.25) * L, u(0.01, 0.03)))
    if kind == "panel":
        return box((u(0.12, 0.35) * L, u(0.008, 0.02), u(0.08, 0.25) * L))
    if kind == "bracket":
        return l_bracket(u(0.06, 0.15) * L, u(0.06, 0.15) * L, u(0.004, 0.012), u(0.04, 0.12) * L)
    if kind == "rail":
        return channel_rail(u(0.4, 0.75) * L, u(0.02, 0.05), u(0.015, 0.04), u(0.003, 0.006))
    raise ValueError(f"unknown part kind {kind!r}")


def _fits(rect: np.ndarray, others: list[np.ndarray], L: float, clearance: float) -> bool:
    """Inside the layout area and clear of the other footprints."""
    if np.abs(rect).max() > HALF_AREA * L:
        return False
    return not any(rectangles_overlap(rect, o, clearance) for o in others)


def _place(rng: np.random.Generator, name: str, kind: str, L: float, others: list[np.ndarray],
           tries: int = 200) -> Part | None:
    """A part of ``kind`` at a random free place (None when none was found in ``tries`` draws)."""
    shape = draw_shape(kind, rng, L)
    for _ in range(tries):
        part = Part(name, kind, shape, float(rng.uniform(0, np.pi)), rng.uniform(-HALF_AREA * L, HALF_AREA * L, 2))
        if _fits(part.rect, others, L, CLEARANCE * L):
            return part
    return None


def draw_parts(rng: np.random.Generator, L: float, n: int, taken: list[np.ndarray] | None = None, start: int = 0
               ) -> list[Part]:
    """Up to ``n`` parts of random kinds at free places (clear of ``taken`` footprints), named ``<kind>_<k>``."""
    others = list(taken or [])
    parts: list[Part] = []
    for attempt in range(4 * n):  # a crowded floor may refuse a large part: draw another kind
        if len(parts) == n:
            break
        kind = str(rng.choice(KINDS, p=KIND_WEIGHTS))
        part = _place(rng, f"{kind}_{start + attempt:02d}", kind, L, others)
        if part is not None:
            parts.append(part)
            others.append(part.rect)
    return parts


def _move(rng: np.random.Generator, part: Part, others: list[np.ndarray], L: float, scale: float) -> Part | None:
    """The part moved by a random displacement (mostly 1–10 × ``scale``, sometimes large), or None."""
    for _ in range(60):
        large = rng.random() < LARGE_MOVE_SHARE
        size = rng.uniform(*LARGE_MOVE) * L if large else min(rng.uniform(1.0, 10.0) * scale, LARGE_MOVE[1] * L)
        angle = rng.uniform(0, 2 * np.pi)
        moved = part.moved_to(part.xy + size * np.array([np.cos(angle), np.sin(angle)]))
        # a small move must not be refused for the gap it leaves: a quarter of the usual clearance
        if _fits(moved.rect, others, L, CLEARANCE * L / 4):
            return moved
    return None


def draw_layout(rng: np.random.Generator, L: float, move_scale: float) -> Layout:
    """The CAD (6–14 parts on a floor plate) and the as-is scene: 1–2 removed, 1–2 moved, 1–3 added."""
    cad = {p.name: p for p in draw_parts(rng, L, int(rng.integers(6, 15)))}
    names = list(cad)
    removed = [str(n) for n in rng.choice(names, size=int(rng.integers(1, 3)), replace=False)]
    rest = [n for n in names if n not in removed]
    asis = {n: cad[n] for n in rest}
    states = {n: ("removed" if n in removed else "unchanged") for n in names}
    displacements: dict[str, list[float]] = {}
    want = int(rng.integers(1, 3))
    for name in (str(n) for n in rng.permutation(rest)):
        if len(displacements) == want:
            break
        others = [p.rect for n, p in asis.items() if n != name]
        moved = _move(rng, cad[name], others, L, move_scale)
        if moved is not None:
            asis[name] = moved
            states[name] = "moved"
            displacements[name] = [float(v) for v in (*(moved.xy - cad[name].xy), 0.0)]
    taken = [p.rect for p in cad.values()] + [p.rect for p in asis.values()]
    # numbered from 100: the CAD's names use at most 4 × 14 attempt numbers, and a name must not hint at the truth
    for part in draw_parts(rng, L, int(rng.integers(1, 4)), taken=taken, start=100):
        asis[part.name] = part
        states[part.name] = "new"
    return Layout(side=L, floor=floor_plate(L, L), cad=cad, asis=asis, states={"floor": "unchanged", **states},
                  displacements=displacements)
