"""Parametric, stochastic, context-sensitive L-systems (Prusinkiewicz and
Lindenmayer, ABOP ch. 1; the Lparser symbol set of seed 003).

A string is a list of modules (symbol, params). A symbol is one character;
parameters are floats: `F(0.5)`, `A(1, 2)`. Rules are applied in parallel.

Expressions (rule arguments and conditions) are parsed with Python's `ast`
and evaluated by a small interpreter over a whitelist (numbers, names,
arithmetic, comparisons, and/or/not, a few math functions, rand(a, b)):
config text is data and is never passed to eval.

Errors are InputError with the species and rule named: an undefined symbol
(neither a turtle command, nor the predecessor of a rule, nor declared
passive), an undefined name in an expression, a string that would grow past
`max_modules` (with its size and the projected size; memory stays bounded
because the check runs while the string is built).
"""
from __future__ import annotations

import ast
import math
import random
from dataclasses import dataclass
from typing import Any, Callable, Sequence

from pipeline.errors import InputError

# Turtle commands (turtle.py gives their meaning). L is this project's leaf.
TURTLE_SYMBOLS = frozenset("FZfzg.+-&^<>/\\|%$~t!?'\":;c[]{}@L")
Module = tuple[str, tuple[float, ...]]


class LSystemSizeError(InputError):
    pass


# ---------------------------------------------------------------- expressions

_FUNCS: dict[str, Callable[..., float]] = {
    "sin": math.sin, "cos": math.cos, "tan": math.tan, "asin": math.asin, "acos": math.acos,
    "atan": math.atan, "atan2": math.atan2, "sqrt": math.sqrt, "exp": math.exp, "log": math.log,
    "abs": abs, "min": min, "max": max, "floor": math.floor, "ceil": math.ceil, "pow": math.pow,
    "rad": math.radians, "deg": math.degrees,
    "clamp": lambda x, lo, hi: max(lo, min(hi, x)),
}
_CONSTS = {"pi": math.pi, "e": math.e}
_BINOPS = {ast.Add: lambda a, b: a + b, ast.Sub: lambda a, b: a - b, ast.Mult: lambda a, b: a * b,
           ast.Div: lambda a, b: a / b, ast.Pow: lambda a, b: a ** b, ast.Mod: lambda a, b: a % b,
           ast.FloorDiv: lambda a, b: a // b}
_CMPOPS = {ast.Lt: lambda a, b: a < b, ast.LtE: lambda a, b: a <= b, ast.Gt: lambda a, b: a > b,
           ast.GtE: lambda a, b: a >= b, ast.Eq: lambda a, b: a == b, ast.NotEq: lambda a, b: a != b}


class ExprError(ValueError):
    pass


def compile_expr(src: str, names: Sequence[str]) -> Callable[[dict, random.Random], float]:
    """Compile an expression over `names` into fn(env, rng)."""
    try:
        tree = ast.parse(src.strip(), mode="eval")
    except SyntaxError as e:
        raise ExprError(f"cannot parse expression {src!r}: {e.msg}") from None
    known = set(names)

    def build(node):
        if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)) and not isinstance(node.value, bool):
            v = float(node.value)
            return lambda env, rng: v
        if isinstance(node, ast.Name):
            n = node.id
            if n in known:
                return lambda env, rng: env[n]
            if n in _CONSTS:
                v = _CONSTS[n]
                return lambda env, rng: v
            raise ExprError(f"unknown name {n!r} in {src!r} (known: {', '.join(sorted(known | set(_CONSTS))) or 'none'})")
        if isinstance(node, ast.UnaryOp):
            a = build(node.operand)
            if isinstance(node.op, ast.USub):
                return lambda env, rng: -a(env, rng)
            if isinstance(node.op, ast.UAdd):
                return a
            if isinstance(node.op, ast.Not):
                return lambda env, rng: float(not a(env, rng))
        if isinstance(node, ast.BinOp) and type(node.op) in _BINOPS:
            f, a, b = _BINOPS[type(node.op)], build(node.left), build(node.right)
            return lambda env, rng: f(a(env, rng), b(env, rng))
        if isinstance(node, ast.BoolOp):
            parts = [build(v) for v in node.values]
            if isinstance(node.op, ast.And):
                return lambda env, rng: float(all(p(env, rng) for p in parts))
            return lambda env, rng: float(any(p(env, rng) for p in parts))
        if isinstance(node, ast.Compare):
            first = build(node.left)
            ops = [(_CMPOPS[type(o)], build(c)) for o, c in zip(node.ops, node.comparators) if type(o) in _CMPOPS]
            if len(ops) != len(node.ops):
                raise ExprError(f"unsupported comparison in {src!r}")

            def cmp(env, rng):
                left = first(env, rng)
                for f, c in ops:
                    right = c(env, rng)
                    if not f(left, right):
                        return 0.0
                    left = right
                return 1.0
            return cmp
        if isinstance(node, ast.IfExp):
            t, a, b = build(node.test), build(node.body), build(node.orelse)
            return lambda env, rng: a(env, rng) if t(env, rng) else b(env, rng)
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and not node.keywords:
            args = [build(a) for a in node.args]
            if node.func.id == "rand":
                if len(args) != 2:
                    raise ExprError(f"rand takes (low, high) in {src!r}")
                lo, hi = args
                return lambda env, rng: lo(env, rng) + (hi(env, rng) - lo(env, rng)) * rng.random()
            if node.func.id in _FUNCS:
                f = _FUNCS[node.func.id]
                return lambda env, rng: float(f(*[a(env, rng) for a in args]))
            raise ExprError(f"unknown function {node.func.id!r} in {src!r} (allowed: {', '.join(sorted(_FUNCS))}, rand)")
        raise ExprError(f"unsupported syntax {type(node).__name__} in {src!r}")

    return build(tree.body)


# ---------------------------------------------------------------- module strings

def split_modules(text: str) -> list[tuple[str, list[str]]]:
    """'F(1,2) [+A]' -> [('F', ['1', '2']), ('[', []), ('+', []), ('A', []), (']', [])]."""
    out: list[tuple[str, list[str]]] = []
    i, n = 0, len(text)
    while i < n:
        c = text[i]
        if c.isspace():
            i += 1
            continue
        if c in "(),":
            raise ExprError(f"unexpected {c!r} at position {i} of {text!r}")
        args: list[str] = []
        j = i + 1
        while j < n and text[j].isspace():
            j += 1
        if j < n and text[j] == "(":
            depth, k, start = 0, j, j + 1
            while k < n:
                if text[k] == "(":
                    depth += 1
                elif text[k] == ")":
                    depth -= 1
                    if depth == 0:
                        break
                elif text[k] == "," and depth == 1:
                    args.append(text[start:k])
                    start = k + 1
                k += 1
            if k >= n:
                raise ExprError(f"unclosed '(' after {c!r} in {text!r}")
            args.append(text[start:k])
            if len(args) == 1 and not args[0].strip():
                args = []
            if any(not a.strip() for a in args):
                raise ExprError(f"empty argument in {c}({text[j + 1:k]}) of {text!r}")
            i = k + 1
        else:
            i += 1
        out.append((c, args))
    return out


def _formals(text: str, what: str) -> list[tuple[str, list[str]]]:
    mods = split_modules(text)
    for sym, args in mods:
        for a in args:
            if not a.strip().isidentifier():
                raise ExprError(f"{what} {text!r}: formal parameter {a.strip()!r} must be a name")
    return [(s, [a.strip() for a in args]) for s, args in mods]


@dataclass
class _Rule:
    index: int
    sym: str
    formals: list[str]
    left: list[tuple[str, list[str]]]
    right: list[tuple[str, list[str]]]
    cond: Callable | None
    succ: list[tuple[str, list[Callable]]]
    p: float
    text: str

    @property
    def tier(self) -> int:
        return 0 if (self.left or self.right) else 1


@dataclass
class LSystem:
    """A compiled L-system ready to derive."""

    axiom: list[Module]
    rules: dict[str, list[_Rule]]
    ignore: frozenset[str]
    has_context: bool
    name: str
    consts: dict[str, float]

    def derive(self, iterations: int, seed: int, max_modules: int, progress: Callable[[int, int], None] | None = None) -> list[Module]:
        rng = random.Random(seed)
        s = list(self.axiom)
        for it in range(iterations):
            s = self._step(s, rng, it, iterations, max_modules)
            if progress:
                progress(it + 1, len(s))
        return s

    def _evaluate(self, rule: "_Rule", env: dict, evaluate: Callable[[], Any]) -> Any:
        """A rule's condition or successor values, or an InputError naming the
        species and the rule: division by zero, overflow, math domain errors
        and results that are not finite numbers."""
        try:
            value = evaluate()
        except (ArithmeticError, ValueError, TypeError) as e:
            raise InputError(f"species {self.name!r}, lsystem.rules[{rule.index}] ({rule.text}): {e} "
                             f"(with {_shown(env, self.consts)})") from None
        values = [value] if not isinstance(value, list) else [v for _, args in value for v in args]
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
            raise InputError(f"species {self.name!r}, lsystem.rules[{rule.index}] ({rule.text}): gives "
                             f"{[v for v in values if not (isinstance(v, (int, float)) and math.isfinite(v))][0]!r}, "
                             f"not a finite number (with {_shown(env, self.consts)})")
        return value

    # one parallel rewriting step
    def _step(self, s: list[Module], rng: random.Random, it: int, iterations: int, max_modules: int) -> list[Module]:
        match = _bracket_match(s) if self.has_context else None
        out: list[Module] = []
        extend, append = out.extend, out.append
        rules = self.rules
        for i, mod in enumerate(s):
            cands = rules.get(mod[0])
            if not cands:
                append(mod)
                continue
            chosen = None
            env = None
            tier = None
            pool: list[tuple[_Rule, dict]] = []
            for r in cands:
                if tier is not None and r.tier != tier:
                    break  # rules are sorted by tier: context-sensitive first
                if len(r.formals) != len(mod[1]):
                    continue
                e = dict(self.consts)
                e.update(zip(r.formals, mod[1]))
                if r.left and not _match_left(s, i, r.left, self.ignore, match, e):
                    continue
                if r.right and not _match_right(s, i, r.right, self.ignore, match, e):
                    continue
                if r.cond is not None and not self._evaluate(r, e, lambda: r.cond(e, rng)):
                    continue
                pool.append((r, e))
                tier = r.tier
            if not pool:
                append(mod)
                continue
            if len(pool) == 1 and pool[0][0].p >= 1.0:
                chosen, env = pool[0]
            else:
                total = sum(r.p for r, _ in pool)
                x = rng.random() * max(total, 1.0)
                acc = 0.0
                for r, e in pool:
                    acc += r.p
                    if x < acc:
                        chosen, env = r, e
                        break
            if chosen is None:  # probability left over: the module stays
                append(mod)
                continue
            extend(self._evaluate(chosen, env, lambda: [(sym, tuple(a(env, rng) for a in args))
                                                         for sym, args in chosen.succ]))
            if len(out) > max_modules:
                done = i + 1
                projected = len(s) * len(out) / done
                growth = projected / max(len(s), 1)
                final = projected * growth ** (iterations - it - 1)
                raise LSystemSizeError(
                    f"species {self.name!r}: the L-system string grows past max_modules = {max_modules:,} in iteration "
                    f"{it + 1} of {iterations} ({len(out):,} modules after rewriting {done:,} of {len(s):,}; about "
                    f"{projected:,.0f} at the end of this iteration, about {final:.3g} after all {iterations}). "
                    f"Lower lsystem.iterations or raise plants.max_modules.")
        return out


def _shown(env: dict, consts: dict) -> str:
    shown = ", ".join(f"{k} = {v!r}" for k, v in env.items() if k not in consts or consts[k] != v)
    return shown or "no parameters"


def _bracket_match(s: list[Module]) -> list[int]:
    match = [-1] * len(s)
    stack = []
    for i, (sym, _) in enumerate(s):
        if sym == "[":
            stack.append(i)
        elif sym == "]" and stack:
            j = stack.pop()
            match[i], match[j] = j, i
    return match


def _bind(ctx_mod: tuple[str, list[str]], mod: Module, env: dict) -> bool:
    sym, formals = ctx_mod
    if mod[0] != sym or (formals and len(formals) != len(mod[1])):
        return False
    for name, val in zip(formals, mod[1]):
        env[name] = val
    return True


def _match_left(s, i, ctx, ignore, match, env) -> bool:
    """ABOP left context: walk toward the root, skipping ignored symbols and
    whole side branches, stepping out of the branch we are in."""
    j, k = i - 1, len(ctx) - 1
    while k >= 0:
        while j >= 0:
            sym = s[j][0]
            if sym == "]":
                j = match[j] - 1 if match[j] >= 0 else -1
            elif sym == "[" or sym in ignore:
                j -= 1
            else:
                break
        if j < 0 or not _bind(ctx[k], s[j], env):
            return False
        j -= 1
        k -= 1
    return True


def _match_right(s, i, ctx, ignore, match, env) -> bool:
    """ABOP right context: the next module on this axis, skipping ignored
    symbols and whole side branches; a ']' ends the axis."""
    j, k, n = i + 1, 0, len(s)
    while k < len(ctx):
        while j < n:
            sym = s[j][0]
            if sym == "[":
                j = match[j] + 1 if match[j] >= 0 else n
            elif sym in ignore:
                j += 1
            else:
                break
        if j >= n or s[j][0] == "]" or not _bind(ctx[k], s[j], env):
            return False
        j += 1
        k += 1
    return True


def compile_lsystem(spec, name: str) -> LSystem:
    """Check and compile a LSystemSpec (species.py). Raises InputError naming
    the species, the rule and the problem."""
    consts = dict(spec.constants)
    for c in consts:
        if not c.isidentifier():
            raise InputError(f"species {name!r}: constant name {c!r} must be a name")
    rule_syms = set()
    raw_rules = []
    for idx, r in enumerate(spec.rules):
        where = f"species {name!r}, lsystem.rules[{idx}] ({r.pred} -> {r.succ})"
        try:
            pred = _formals(r.pred, "predecessor")
            if len(pred) != 1:
                raise ExprError(f"predecessor {r.pred!r} must be exactly one module")
            left = _formals(r.left, "left context") if r.left else []
            right = _formals(r.right, "right context") if r.right else []
        except ExprError as e:
            raise InputError(f"{where}: {e}") from None
        sym, formals = pred[0]
        if sym in "[]{}":
            raise InputError(f"{where}: brackets cannot be rewritten")
        if len(set(formals)) != len(formals):
            raise InputError(f"{where}: repeated formal parameter")
        rule_syms.add(sym)
        raw_rules.append((idx, r, where, sym, formals, left, right))

    defined = TURTLE_SYMBOLS | rule_syms | set(spec.passive)

    def check_symbols(mods, where):
        for sym, _ in mods:
            if sym not in defined:
                raise InputError(
                    f"{where}: undefined symbol {sym!r}: it is no turtle command, no rule rewrites it and it is not in "
                    f"lsystem.passive (turtle commands: {''.join(sorted(TURTLE_SYMBOLS))}; rules: {''.join(sorted(rule_syms)) or 'none'})")

    def check_brackets(mods, where):
        depth = 0
        for sym, _ in mods:
            depth += {"[": 1, "]": -1}.get(sym, 0)
            if depth < 0:
                raise InputError(f"{where}: ']' without '['")
        if depth:
            raise InputError(f"{where}: {depth} unclosed '['")

    arities: dict[str, set[int]] = {}
    for _, _, _, sym, formals, _, _ in raw_rules:
        arities.setdefault(sym, set()).add(len(formals))

    rules: dict[str, list[_Rule]] = {}
    has_context = False
    for idx, r, where, sym, formals, left, right in raw_rules:
        names = list(formals) + [n for _, fs in left + right for n in fs] + list(consts)
        try:
            succ_mods = split_modules(r.succ)
            check_symbols(succ_mods, where)
            check_symbols(left + right, where)
            check_brackets(succ_mods, where)
            succ = []
            for s_sym, args in succ_mods:
                if s_sym in arities and len(args) not in arities[s_sym]:
                    raise ExprError(f"{s_sym} is given {len(args)} parameter(s) but its rules take "
                                    f"{' or '.join(str(a) for a in sorted(arities[s_sym]))}")
                fns = [compile_expr(a, names) for a in args]
                succ.append((s_sym, fns))
            cond = compile_expr(r.cond, names) if r.cond.strip() else None
        except ExprError as e:
            raise InputError(f"{where}: {e}") from None
        has_context |= bool(left or right)
        rules.setdefault(sym, []).append(_Rule(idx, sym, formals, left, right, cond, succ, r.p, f"{r.pred} -> {r.succ}"))
    for sym in rules:
        rules[sym].sort(key=lambda rr: (rr.tier, rr.index))

    where = f"species {name!r}, lsystem.axiom {spec.axiom!r}"
    try:
        ax_mods = split_modules(spec.axiom)
        check_symbols(ax_mods, where)
        check_brackets(ax_mods, where)
        rng = random.Random(0)
        axiom = []
        for sym, args in ax_mods:
            if sym in arities and len(args) not in arities[sym]:
                raise ExprError(f"{sym} is given {len(args)} parameter(s) but its rules take "
                                f"{' or '.join(str(a) for a in sorted(arities[sym]))}")
            values = tuple(compile_expr(a, list(consts))(consts, rng) for a in args)
            if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
                raise ExprError(f"{sym}{values} holds a value that is not a finite number")
            axiom.append((sym, values))
    except (ExprError, ArithmeticError, ValueError, TypeError) as e:
        raise InputError(f"{where}: {e}") from None
    ignore = frozenset(spec.ignore) - {"[", "]"}
    return LSystem(axiom, rules, ignore, has_context, name, consts)


def to_text(s: Sequence[Module]) -> str:
    """A derived string as text (for tests and debugging)."""
    parts = []
    for sym, params in s:
        parts.append(sym + ("(" + ",".join(f"{p:g}" for p in params) + ")" if params else ""))
    return "".join(parts)
