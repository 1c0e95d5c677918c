"""The 3D turtle (ABOP ch. 1.5; Lparser's symbol set, seed 003): a derived
string -> a skeleton of segments with radius and frame, leaves and polygons.

Frame: heading H, left L, up U (H x L = U). Y is up: the turtle starts at the
origin heading +Y, with L = -X and U = +Z. Angles in degrees.

    F(l) Z(l)   draw a segment of length l (default: current length; Z: half)
    f(l) z(l)   move without drawing; inside { } also records a polygon vertex
    g(l)        move without drawing or recording
    .           record a polygon vertex without moving
    + -         turn left / right about U         & ^   pitch down / up about L
    < > \\ /    roll left / right about H         |     turn 180 degrees
    $           roll until L is horizontal        ~(a)  random turn, pitch and roll within +-a
    t(e)        bend toward the tropism vector with strength e
    ! ?         radius * / / width_ratio          ' "   length * / / length_ratio
    : ;         angle * / / angle_ratio           c(n)  colour index n (or +1)
    [ ]         push / pop the state              { }   open / close a polygon (a leaf)
    %           cut off the rest of the branch    @     end of the string
    L(s)        a leaf of the species' shape, scaled by s, along H with normal U
Every other symbol is a nonterminal and draws nothing.
"""
from __future__ import annotations

import math
import random
from dataclasses import dataclass, field

import numpy as np

from .lsystem import Module


@dataclass
class Skeleton:
    p0: np.ndarray  # (n, 3) segment start
    p1: np.ndarray  # (n, 3) segment end
    heading: np.ndarray  # (n, 3)
    left: np.ndarray  # (n, 3)
    up: np.ndarray  # (n, 3)
    radius: np.ndarray  # (n,) radius from the string (turtle model)
    parent: np.ndarray  # (n,) int, -1 for a root
    cont: np.ndarray  # (n,) bool: continues its parent's axis (no '[' between)
    order: np.ndarray  # (n,) int branch order (bracket depth)
    colour: np.ndarray  # (n,) int
    leaf_pos: np.ndarray  # (m, 3)
    leaf_h: np.ndarray
    leaf_l: np.ndarray
    leaf_u: np.ndarray
    leaf_scale: np.ndarray  # (m,)
    leaf_parent: np.ndarray  # (m,) int segment the leaf hangs on, -1 if none
    polygons: list = field(default_factory=list)  # [(k, 3) float arrays]
    polygon_parent: list = field(default_factory=list)

    @property
    def n_segments(self) -> int:
        return len(self.p0)

    @property
    def n_leaves(self) -> int:
        return len(self.leaf_pos)


def _rot(a, b, ang):
    """Rotate the orthonormal pair (a, b) by ang in their plane."""
    c, s = math.cos(ang), math.sin(ang)
    return ([a[0] * c + b[0] * s, a[1] * c + b[1] * s, a[2] * c + b[2] * s],
            [b[0] * c - a[0] * s, b[1] * c - a[1] * s, b[2] * c - a[2] * s])


def _cross(a, b):
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def _norm(a):
    n = math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
    return [a[0] / n, a[1] / n, a[2] / n] if n > 0 else a


def _axis_rot(v, k, ang):
    """Rodrigues: v rotated about unit axis k by ang."""
    c, s = math.cos(ang), math.sin(ang)
    kv = _cross(k, v)
    d = (k[0] * v[0] + k[1] * v[1] + k[2] * v[2]) * (1 - c)
    return [v[i] * c + kv[i] * s + k[i] * d for i in range(3)]


def _orthonormalize(st):
    h = _norm(st[1])
    l_ = st[2]
    d = h[0] * l_[0] + h[1] * l_[1] + h[2] * l_[2]
    l_ = _norm([l_[0] - d * h[0], l_[1] - d * h[1], l_[2] - d * h[2]])
    st[1], st[2], st[3] = h, l_, _cross(h, l_)


def interpret(modules: list[Module], spec, seed: int) -> Skeleton:
    """Run the turtle over a derived string. `spec` is the LSystemSpec (default
    length, angle, ratios, jitter, tropism) and the WoodSpec radius via
    spec_radius. Random turns (~) and jitter use a generator seeded by `seed`."""
    turtle = _Turtle(spec, seed)
    n = len(modules)
    i = 0
    while i < n:
        sym, params = modules[i]
        i += 1
        if sym == "%":
            i = _skip_branch(modules, i)
        elif sym == "@":
            break
        else:
            turtle.step(sym, params)
    return turtle.skeleton()


def _skip_branch(modules: list[Module], i: int) -> int:
    """% cuts the rest of the branch: the index of its closing ] (or the end)."""
    n = len(modules)
    depth = 0
    while i < n:
        s2 = modules[i][0]
        if s2 == "[":
            depth += 1
        elif s2 == "]":
            if depth == 0:
                break
            depth -= 1
        i += 1
    return i


class _Turtle:
    """The turtle's state and what it drew so far.

    state: [pos, H, L, U, length, radius, angle(rad), colour, last_seg, cont, order]"""

    def __init__(self, spec, seed: int):
        ls = self.ls = spec.lsystem
        self.rng = random.Random(seed)
        self.deg = deg = math.pi / 180.0
        self.aj = ls.angle_jitter * deg
        self.lj = ls.length_jitter
        self.trop = _norm(list(ls.tropism)) if any(ls.tropism) else [0.0, 0.0, 0.0]
        self.trop_e = ls.tropism_strength
        self.st = [[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0],
                   ls.length, spec.wood.radius, ls.angle * deg, 0, -1, False, 0]
        self.stack: list = []
        self.polys: list[list] = []
        self.seg = {k: [] for k in ("p0", "p1", "h", "l", "u", "r", "parent", "cont", "order", "colour")}
        self.leaf = {k: [] for k in ("pos", "h", "l", "u", "s", "parent")}
        self.polygons, self.polygon_parent = [], []

    def step(self, sym: str, params) -> None:
        """One module (but % and @, which the string's walk handles)."""
        if sym in "FZ":
            self.draw(sym, params)
        elif sym in "fzg":
            self.move(sym, params)
        elif sym == ".":
            if self.polys:
                self.polys[-1].append(self.st[0])
        elif sym in ("+", "-", "&", "^") or sym in "<>\\/":
            self.turn(sym, params)
        elif sym in ("|", "$", "~", "t"):
            self.reorient(sym, params)
        elif sym in ("!", "?", "'", '"', ":", ";", "c"):
            self.rescale(sym, params)
        elif sym in ("[", "]", "{", "}"):
            self.bracket(sym)
        elif sym == "L":
            self.add_leaf(params)

    def angle_of(self, params):
        a = params[0] * self.deg if params else self.st[6]
        return a + (self.rng.uniform(-self.aj, self.aj) if self.aj > 0 else 0.0)

    def bend(self, e):
        """Tropism: turn H toward the tropism vector by e * |H x T|."""
        st = self.st
        if e <= 0:
            return
        h = st[1]
        ax = _cross(h, self.trop)
        mag = math.sqrt(ax[0] ** 2 + ax[1] ** 2 + ax[2] ** 2)
        if mag < 1e-9:
            return
        ax = [ax[0] / mag, ax[1] / mag, ax[2] / mag]
        ang = e * mag
        st[1], st[2], st[3] = _axis_rot(st[1], ax, ang), _axis_rot(st[2], ax, ang), _axis_rot(st[3], ax, ang)

    def draw(self, sym: str, params) -> None:
        """F (Z: half length): a segment forward, then tropism."""
        st, seg = self.st, self.seg
        ln = params[0] if params else st[4]
        if sym == "Z":
            ln *= 0.5
        if self.lj > 0:
            ln *= 1.0 + self.rng.uniform(-self.lj, self.lj)
        if ln <= 0:
            return
        p, h = st[0], st[1]
        q = [p[0] + h[0] * ln, p[1] + h[1] * ln, p[2] + h[2] * ln]
        seg["p0"].append(p)
        seg["p1"].append(q)
        seg["h"].append(h)
        seg["l"].append(st[2])
        seg["u"].append(st[3])
        seg["r"].append(st[5])
        seg["parent"].append(st[8])
        seg["cont"].append(st[9])
        seg["order"].append(st[10])
        seg["colour"].append(st[7])
        st[0] = q
        st[8] = len(seg["p0"]) - 1
        st[9] = True
        self.bend(self.trop_e)
        _orthonormalize(st)

    def move(self, sym: str, params) -> None:
        """f (z: half length) moves without drawing, adding a polygon vertex; g adds none."""
        st = self.st
        ln = params[0] if params else st[4]
        if sym == "z":
            ln *= 0.5
        p, h = st[0], st[1]
        st[0] = [p[0] + h[0] * ln, p[1] + h[1] * ln, p[2] + h[2] * ln]
        st[8], st[9] = -1, False
        if sym != "g" and self.polys:
            self.polys[-1].append(st[0])

    def turn(self, sym: str, params) -> None:
        """+ - turn, & ^ pitch, < > \\ / roll by the angle (jittered)."""
        st = self.st
        a = self.angle_of(params)
        if sym == "+" or sym == "-":
            st[1], st[2] = _rot(st[1], st[2], a if sym == "+" else -a)
        elif sym == "&" or sym == "^":
            # pitch down: H toward -U
            st[1], st[3] = _rot(st[1], [-x for x in st[3]], a if sym == "&" else -a)
            st[3] = [-x for x in st[3]]
        else:
            st[2], st[3] = _rot(st[2], st[3], a if sym in "<\\" else -a)

    def reorient(self, sym: str, params) -> None:
        """| turns around, $ rolls L horizontal, ~ turns at random, t bends by tropism."""
        st, rng = self.st, self.rng
        if sym == "|":
            st[1], st[2] = _rot(st[1], st[2], math.pi)
        elif sym == "$":
            h = st[1]
            l_ = _cross([0.0, 1.0, 0.0], h)
            if l_[0] ** 2 + l_[1] ** 2 + l_[2] ** 2 > 1e-12:
                st[2] = _norm(l_)
                st[3] = _cross(h, st[2])
        elif sym == "~":
            a = params[0] * self.deg if params else st[6]
            st[1], st[2] = _rot(st[1], st[2], rng.uniform(-a, a))
            h, mu = _rot(st[1], [-x for x in st[3]], rng.uniform(-a, a))
            st[1], st[3] = h, [-x for x in mu]
            st[2], st[3] = _rot(st[2], st[3], rng.uniform(-a, a))
            _orthonormalize(st)
        else:
            self.bend(params[0] if params else (self.trop_e or 0.2))
            _orthonormalize(st)

    def rescale(self, sym: str, params) -> None:
        """! ? width, ' " length, : ; angle times or over a ratio; c sets the colour."""
        st, ls = self.st, self.ls
        if sym == "!":
            st[5] *= params[0] if params else ls.width_ratio
        elif sym == "?":
            r = params[0] if params else ls.width_ratio
            st[5] = st[5] / r if r > 0 else st[5]
        elif sym == "'":
            st[4] *= params[0] if params else ls.length_ratio
        elif sym == '"':
            r = params[0] if params else ls.length_ratio
            st[4] = st[4] / r if r > 0 else st[4]
        elif sym == ":":
            st[6] *= params[0] if params else ls.angle_ratio
        elif sym == ";":
            r = params[0] if params else ls.angle_ratio
            st[6] = st[6] / r if r > 0 else st[6]
        else:
            st[7] = int(params[0]) if params else st[7] + 1

    def bracket(self, sym: str) -> None:
        """[ ] push and pop the state (a branch); { } open and close a polygon."""
        if sym == "[":
            self.stack.append(self.st)
            self.st = list(self.st)
            self.st[9] = False
            self.st[10] = self.st[10] + 1
        elif sym == "]":
            if self.stack:
                self.st = self.stack.pop()
        elif sym == "{":
            self.polys.append([])
        elif self.polys:
            pts = self.polys.pop()
            if len(pts) >= 3:
                self.polygons.append(np.asarray(pts, dtype=np.float64))
                self.polygon_parent.append(self.st[8])

    def add_leaf(self, params) -> None:
        st, leaf = self.st, self.leaf
        s = params[0] if params else 1.0
        if s > 0:
            leaf["pos"].append(st[0])
            leaf["h"].append(st[1])
            leaf["l"].append(st[2])
            leaf["u"].append(st[3])
            leaf["s"].append(s)
            leaf["parent"].append(st[8])

    def skeleton(self) -> Skeleton:
        seg, leaf = self.seg, self.leaf

        def arr(x, shape=(0, 3), dtype=np.float64):
            return np.asarray(x, dtype=dtype).reshape((-1,) + shape[1:]) if len(x) else np.zeros(shape, dtype)

        return Skeleton(
            p0=arr(seg["p0"]), p1=arr(seg["p1"]), heading=arr(seg["h"]), left=arr(seg["l"]), up=arr(seg["u"]),
            radius=arr(seg["r"], (0,)), parent=arr(seg["parent"], (0,), np.int64), cont=arr(seg["cont"], (0,), bool),
            order=arr(seg["order"], (0,), np.int64), colour=arr(seg["colour"], (0,), np.int64),
            leaf_pos=arr(leaf["pos"]), leaf_h=arr(leaf["h"]), leaf_l=arr(leaf["l"]), leaf_u=arr(leaf["u"]),
            leaf_scale=arr(leaf["s"], (0,)), leaf_parent=arr(leaf["parent"], (0,), np.int64),
            polygons=self.polygons, polygon_parent=self.polygon_parent,
        )


def pipe_radii(sk: Skeleton, tip_radius: float, exponent: float, leaf_weight: float) -> np.ndarray:
    """Pipe model (da Vinci): every tip carries one pipe of radius tip_radius;
    a segment's cross-section area ~ r^e adds up the pipes downstream, so
    r = tip_radius * n^(1/e) with n = tips downstream (a leaf counts leaf_weight).
    Parents always precede children in the skeleton, so one reverse sweep suffices."""
    n = sk.n_segments
    if n == 0:
        return np.zeros(0)
    has_child = np.zeros(n, bool)
    par = sk.parent
    has_child[par[par >= 0]] = True
    tips = np.where(has_child, 0.0, 1.0)
    lp = sk.leaf_parent[sk.leaf_parent >= 0]
    np.add.at(tips, lp, leaf_weight)
    tips_l = tips.tolist()
    par_l = par.tolist()
    for s in range(n - 1, -1, -1):
        p = par_l[s]
        if p >= 0:
            tips_l[p] += tips_l[s]
    return tip_radius * np.power(np.maximum(np.asarray(tips_l), 1e-12), 1.0 / exponent)


def path_length(sk: Skeleton) -> tuple[np.ndarray, np.ndarray]:
    """Distance along the skeleton from the root to each segment's start and end."""
    n = sk.n_segments
    seglen = np.linalg.norm(sk.p1 - sk.p0, axis=1) if n else np.zeros(0)
    start = np.zeros(n)
    par = sk.parent.tolist()
    sl = seglen.tolist()
    st = [0.0] * n
    for s in range(n):
        p = par[s]
        st[s] = st[p] + sl[p] if p >= 0 else 0.0
    start = np.asarray(st)
    return start, start + seglen
