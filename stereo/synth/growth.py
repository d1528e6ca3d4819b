"""Tree skeletons grown by space colonization, with radii by the pipe model, for the randomized scenes.

Space colonization (Runions et al. 2007): attraction points fill the crown's envelope; each growth
step, every point pulls the skeleton node nearest to it (within the influence radius), each pulled
node grows one step toward the mean direction of its points (plus a tropism and a random jitter),
and points that a node comes within the kill radius of are consumed. The envelope and the
pre-built trunk and leaders give the training system its form: a cone around one leader (central
leader, tall spindle), two or more leaders in a V or a bowl (open-V, vase), flat tiers along the row
(espalier), a big rounded crown on a clear trunk (park), a narrow crown high up (forest), a thin
stem with a few feathers (young whip), a wide crooked crown (old gnarled tree).

Radii follow the pipe model (da Vinci's rule): a node's radius `r` satisfies `r^e = Σ r_child^e`,
every tip has the same radius, and the exponent `e` is drawn per tree (2–2.5). The skeleton is
coarser than a real tree (a tip stands for a bundle of shoots), so radii above the tips are then
stretched linearly, tips fixed, until the foot of the trunk has the radius drawn for the tree.

A skeleton is in the tree's own frame: metres, the foot of the trunk at the origin, y down (gravity),
x along the row, z across it. Each segment knows its branching order (0: trunk and leaders, 1: the
branches growing out of them, 2 and more: their shoots and twigs) and the axis it belongs to, so a
scene can label a whole first-order branch as one instance.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

#: training systems and tree kinds `grow_tree` knows, and the form each is drawn with (see `FORMS`)
FORM_NAMES = (
    "central_leader",
    "tall_spindle",
    "open_v",
    "espalier",
    "vase",
    "park",
    "forest",
    "whip",
    "gnarled",
)
#: the form used when tree forms are not randomized
DEFAULT_FORM = "central_leader"
_UP = np.array([0.0, -1.0, 0.0])
#: radius (m) of every shoot tip before the pipe model sums them up
TIP_RADIUS_M = (0.0012, 0.0025)


@dataclass(frozen=True)
class GrowthForm:
    """How one kind of tree is grown; ranges are (low, high) drawn uniformly per tree.

    - `height_m`: top of the crown above the ground; `crown_base`: where the crown starts, as a
      fraction of the height (the clear trunk below it has no branches);
    - `width`: crown half-width as a fraction of the height; `envelope`: the crown's shape
      ('cone', 'ellipsoid', 'v', 'bowl', 'tiers');
    - `planar`: the crown is a hedge-like wall along the row (half-thickness 0.2 m across it);
    - `leaders`: how many leaders leave the top of the clear trunk (1: the trunk itself goes on to
      `leader_top` of the height);
    - `attractors`: attraction points in the crown; `jitter`: random part of each growth step
      (relative to the pull); `tropism`: a constant pull added to every step (`(x, y, z)`, y down:
      negative y grows upward, positive droops);
    - `trunk_radius_m`: radius at the foot.
    """

    height_m: tuple[float, float]
    crown_base: tuple[float, float]
    width: tuple[float, float]
    envelope: str
    planar: bool
    leaders: tuple[int, int]
    leader_top: float
    attractors: tuple[int, int]
    jitter: float
    tropism: tuple[float, float, float]
    trunk_radius_m: tuple[float, float]


FORMS: dict[str, GrowthForm] = {
    "central_leader": GrowthForm((2.5, 4.5), (0.15, 0.3), (0.3, 0.45), "cone", False, (1, 1), 0.92, (250, 450), 0.25,
                                 (0.0, -0.1, 0.0), (0.04, 0.10)),
    "tall_spindle": GrowthForm((2.8, 3.8), (0.15, 0.25), (0.12, 0.22), "cone", False, (1, 1), 0.95, (200, 350), 0.2,
                               (0.0, 0.25, 0.0), (0.025, 0.06)),
    "open_v": GrowthForm((2.5, 4.0), (0.12, 0.22), (0.35, 0.5), "v", True, (2, 2), 0.0, (250, 400), 0.25,
                         (0.0, -0.15, 0.0), (0.05, 0.10)),
    "espalier": GrowthForm((1.6, 2.6), (0.2, 0.3), (0.6, 1.0), "tiers", True, (1, 1), 0.95, (200, 350), 0.1,
                           (0.0, 0.05, 0.0), (0.04, 0.08)),
    "vase": GrowthForm((2.5, 4.0), (0.15, 0.25), (0.4, 0.6), "bowl", False, (3, 5), 0.0, (300, 450), 0.3,
                       (0.0, -0.1, 0.0), (0.08, 0.15)),
    "park": GrowthForm((6.0, 12.0), (0.2, 0.35), (0.3, 0.45), "ellipsoid", False, (1, 1), 0.55, (350, 550), 0.3,
                       (0.0, -0.05, 0.0), (0.15, 0.40)),
    "forest": GrowthForm((10.0, 18.0), (0.45, 0.65), (0.12, 0.2), "ellipsoid", False, (1, 1), 0.9, (250, 400), 0.25,
                         (0.0, -0.1, 0.0), (0.15, 0.35)),
    "whip": GrowthForm((1.0, 2.0), (0.3, 0.5), (0.08, 0.15), "cone", False, (1, 1), 0.97, (12, 40), 0.15,
                       (0.0, -0.3, 0.0), (0.007, 0.015)),
    "gnarled": GrowthForm((3.0, 6.0), (0.2, 0.35), (0.45, 0.7), "ellipsoid", False, (2, 3), 0.0, (300, 450), 0.8,
                          (0.0, 0.1, 0.0), (0.15, 0.35)),
}  # fmt: skip


@dataclass(frozen=True)
class Skeleton:
    """A grown tree: `N` segments in the tree's frame (m, foot at the origin, y down).

    - `start`, `end`: `(N, 3)` segment end points (a segment runs from its parent node to its node);
    - `r0`, `r1`: `(N,)` radii (m) at the start and the end;
    - `order`: `(N,)` branching order (0 trunk and leaders, 1 branches, ≥ 2 shoots and twigs);
    - `axis_id`: `(N,)` which axis (a run of segments of one order) each belongs to, `axis_parent` `(A,)`
      the axis each axis grows from (-1 for the trunk);
    - `tip`: `(N,)` whether the segment ends in a shoot tip (where leaves, blossom and fruit go).
    """

    form: str
    start: np.ndarray
    end: np.ndarray
    r0: np.ndarray
    r1: np.ndarray
    order: np.ndarray
    axis_id: np.ndarray
    axis_parent: np.ndarray
    tip: np.ndarray

    @property
    def first_order_root(self) -> np.ndarray:
        """`(N,)` for each segment, the first-order axis it belongs to or grows from (-1 on the trunk)."""
        root = np.full(self.axis_parent.size, -1, dtype=np.int64)
        order_of_axis = np.zeros(self.axis_parent.size, dtype=np.int64)
        order_of_axis[self.axis_id] = self.order
        for axis in range(self.axis_parent.size):  # parents are numbered before their children
            parent = self.axis_parent[axis]
            root[axis] = axis if order_of_axis[axis] == 1 else (root[parent] if parent >= 0 else -1)
        return np.asarray(root[self.axis_id])


def _envelope(form: GrowthForm, height: float, base: float, half_width: float) -> Callable[[np.ndarray], np.ndarray]:
    """Which points `(N, 3)` (tree frame) lie inside the crown's envelope."""
    span = height - base

    def inside(p: np.ndarray) -> np.ndarray:
        h = -p[:, 1]
        t = (h - base) / span  # 0 at the crown's base, 1 at its top
        radial = np.hypot(p[:, 0], p[:, 2])
        in_height = (t >= 0.0) & (t <= 1.0)
        if form.envelope == "cone":
            shape = radial <= half_width * (1.0 - t) + 0.05
        elif form.envelope == "ellipsoid":
            shape = (radial / half_width) ** 2 + ((t - 0.45) / 0.55) ** 2 <= 1.0
        elif form.envelope == "v":  # two arms rising from the centre, along x
            shape = np.abs(np.abs(p[:, 0]) - (0.15 + 0.85 * t) * half_width) <= 0.25 * half_width
        elif form.envelope == "bowl":  # a hollow cone opening upward
            reach = (0.25 + 0.75 * t) * half_width
            shape = (radial <= reach) & (radial >= 0.45 * reach)
        else:  # tiers: thin horizontal layers every 0.4–0.6 m along the row
            tier = np.mod(h - base, 0.5)
            shape = (np.minimum(tier, 0.5 - tier) <= 0.06) & (np.abs(p[:, 0]) <= half_width)
        if form.planar:
            shape &= np.abs(p[:, 2]) <= 0.2
        return np.asarray(in_height & shape)

    return inside


def _attractors(rng: np.random.Generator, inside: Callable[[np.ndarray], np.ndarray], count: int,
                height: float, half_width: float) -> np.ndarray:  # fmt: skip
    """`count` points `(count, 3)` drawn uniformly inside the envelope (rejection sampling)."""
    found: list[np.ndarray] = []
    total = 0
    for _ in range(50):
        p = rng.uniform([-half_width, -height, -half_width], [half_width, 0.0, half_width], size=(4 * count, 3))
        p = p[inside(p)]
        found.append(p)
        total += len(p)
        if total >= count:
            break
    return np.concatenate(found)[:count] if total else np.zeros((0, 3))


class _Nodes:
    """The growing skeleton: node positions, parents and orders, with room for more."""

    def __init__(self) -> None:
        self.pos: list[np.ndarray] = []
        self.parent: list[int] = []
        self.children: list[int] = []
        self.trunk: list[bool] = []

    def add(self, pos: np.ndarray, parent: int, trunk: bool = False) -> int:
        self.pos.append(pos)
        self.parent.append(parent)
        self.children.append(0)
        self.trunk.append(trunk)
        if parent >= 0:
            self.children[parent] += 1
        return len(self.pos) - 1

    def chain(self, start: int, direction: np.ndarray, length: float, step: float, rng: np.random.Generator,
              wiggle: float) -> int:  # fmt: skip
        """A pre-built trunk or leader: nodes every `step` m from node `start` along `direction`."""
        node = start
        for _ in range(max(1, int(round(length / step)))):
            heading = direction + wiggle * rng.normal(size=3)
            node = self.add(self.pos[node] + step * heading / np.linalg.norm(heading), node, trunk=True)
        return node


def grow_tree(rng: np.random.Generator, form_name: str, max_nodes: int = 900) -> Skeleton:
    """Grow one tree of `form_name` (one of `FORM_NAMES`); every random choice comes from `rng`.

    `max_nodes` bounds the skeleton (and so the render cost): far trees need fewer.
    """
    if form_name not in FORMS:
        raise ValueError(f"unknown tree form {form_name!r}; known forms: {', '.join(FORM_NAMES)}")
    form = FORMS[form_name]
    height = rng.uniform(*form.height_m)
    base = height * rng.uniform(*form.crown_base)
    half_width = height * rng.uniform(*form.width)
    step = height / rng.uniform(22.0, 32.0)
    inside = _envelope(form, height, base, half_width)
    points = _attractors(rng, inside, int(rng.integers(*form.attractors, endpoint=True)), height, half_width)
    wiggle = 0.03 + 0.12 * form.jitter
    nodes = _Nodes()
    top = nodes.chain(nodes.add(np.zeros(3), -1, trunk=True), _UP, base, step, rng, wiggle)
    if form.leaders[0] == 1 and form.leader_top > 0:
        nodes.chain(top, _UP, form.leader_top * height - base, step, rng, wiggle)
    else:
        count = int(rng.integers(form.leaders[0], form.leaders[1], endpoint=True))
        turn = rng.uniform(0, 2 * np.pi)
        for k in range(count):
            azimuth = np.pi * k if form.planar else turn + 2 * np.pi * k / count
            lean = np.radians(rng.uniform(30.0, 50.0))
            heading = np.sin(lean) * np.array([np.cos(azimuth), 0.0, np.sin(azimuth)]) + np.cos(lean) * _UP
            nodes.chain(top, heading, 0.3 * (height - base), step, rng, wiggle)
    _colonize(rng, nodes, points, form, step, max_nodes)
    return _skeleton(rng, form_name, form, nodes)


def _colonize(rng: np.random.Generator, nodes: _Nodes, points: np.ndarray, form: GrowthForm, step: float,
              max_nodes: int) -> None:  # fmt: skip
    """Grow `nodes` toward the attraction `points` until none pulls or the node budget is spent."""
    influence, kill = 6.0 * step, 1.6 * step
    tropism = np.array(form.tropism)
    for _ in range(120):
        if len(points) == 0 or len(nodes.pos) >= max_nodes:
            return
        positions = np.array(nodes.pos)
        # a trunk node keeps its trunk child and may grow two side branches; any other node two children
        budget = np.array(nodes.children) < np.where(np.array(nodes.trunk), 3, 2)
        offsets = points[:, None, :] - positions[None, :, :]
        distance = np.sqrt((offsets**2).sum(axis=2))
        distance[:, ~budget] = np.inf
        nearest = distance.argmin(axis=1)
        pulled = distance[np.arange(len(points)), nearest] <= influence
        if not pulled.any():
            return
        grown = 0
        for node in np.unique(nearest[pulled]):
            mine = pulled & (nearest == node)
            pull = (offsets[mine, node] / distance[mine, node][:, None]).sum(axis=0)
            pull /= max(np.linalg.norm(pull), 1e-9)
            heading = pull + tropism + form.jitter * rng.normal(size=3) / np.sqrt(3)
            norm = np.linalg.norm(heading)
            if norm < 1e-6:
                continue
            nodes.add(positions[node] + step * heading / norm, int(node))
            grown += 1
            if len(nodes.pos) >= max_nodes:
                break
        if grown == 0:
            return
        new = np.array(nodes.pos[-grown:])
        reached = (np.sqrt(((points[:, None, :] - new[None, :, :]) ** 2).sum(axis=2)) <= kill).any(axis=1)
        points = points[~reached]


def _skeleton(rng: np.random.Generator, form_name: str, form: GrowthForm, nodes: _Nodes) -> Skeleton:
    """Segments with pipe-model radii, orders and axes from the grown nodes."""
    count = len(nodes.pos)
    parent = np.array(nodes.parent)
    children: list[list[int]] = [[] for _ in range(count)]
    for node in range(1, count):
        children[parent[node]].append(node)
    tip_radius = rng.uniform(*TIP_RADIUS_M)
    base_radius = rng.uniform(*form.trunk_radius_m)
    exponent = rng.uniform(2.0, 2.5)
    pipe = np.zeros(count)  # Σ r^e over the tips above each node; nodes are numbered after their parents
    for node in range(count - 1, -1, -1):
        pipe[node] = sum(pipe[c] for c in children[node]) if children[node] else tip_radius**exponent
    radius = pipe ** (1.0 / exponent)
    radius = tip_radius + (radius - tip_radius) * (base_radius - tip_radius) / max(radius[0] - tip_radius, 1e-9)
    # the child carrying the most pipes (or the trunk's own chain) continues its parent's axis
    order = np.zeros(count, dtype=np.int64)
    axis = np.zeros(count, dtype=np.int64)
    axis_parent = [-1]
    continues = np.zeros(count, dtype=bool)
    for node in range(count):
        if not children[node]:
            continue
        kids = children[node]
        trunk_kids = [c for c in kids if nodes.trunk[c]]
        main = trunk_kids[0] if nodes.trunk[node] and trunk_kids else max(kids, key=lambda c: pipe[c])
        for child in kids:
            if child == main or (nodes.trunk[child] and nodes.trunk[node]):
                order[child], axis[child], continues[child] = order[node], axis[node], child == main
                if child != main:  # a further leader out of the trunk's top: its own order-0 axis
                    axis[child] = len(axis_parent)
                    axis_parent.append(int(axis[node]))
            else:
                order[child] = order[node] + 1
                axis[child] = len(axis_parent)
                axis_parent.append(int(axis[node]))
    positions = np.array(nodes.pos)
    seg = np.arange(1, count)
    r0 = np.where(continues[seg], radius[parent[seg]], radius[seg])
    return Skeleton(
        form_name,
        positions[parent[seg]],
        positions[seg],
        r0,
        radius[seg],
        order[seg],
        axis[seg],
        np.array(axis_parent, dtype=np.int64),
        np.array([not children[n] for n in seg]),
    )
