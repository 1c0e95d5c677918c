"""The L-system engine: parametric, stochastic, context-sensitive rewriting,
and its clear errors."""
import random
import time

import pytest

from pipeline.errors import InputError
from stages.plants.lsystem import LSystemSizeError, compile_expr, compile_lsystem, to_text
from stages.plants.species import LSystemSpec


def derive(axiom, rules, n, seed=0, max_modules=100_000, **kw):
    spec = LSystemSpec.model_validate({"axiom": axiom, "rules": rules, **kw})
    return to_text(compile_lsystem(spec, "t").derive(n, seed, max_modules))


def test_zero_iterations_give_the_axiom():
    assert derive("F(1) A(2)", [{"pred": "A(x)", "succ": "F(x) A(x)"}], 0) == "F(1)A(2)"


def test_parametric_rules_evaluate_expressions():
    assert derive("A(1)", [{"pred": "A(x)", "succ": "F(x) A(x*2)"}], 3) == "F(1)F(2)F(4)A(8)"


def test_constants_conditions_and_lparser_strings():
    rules = [{"pred": "A(x)", "cond": "x < k", "succ": "F A(x+1)"}, {"pred": "A(x)", "cond": "x >= k", "succ": "L"}, "F=FF"]
    out = derive("A(0)", rules, 3, constants={"k": 2})
    assert out == "FFFFFFL"  # F A(1) -> FFF A(2) -> FFFFFF L


def test_context_sensitive_signal_propagation():
    """ABOP fig. 1.31 style: a signal b travels along a string of a's."""
    rules = [{"pred": "a", "left": "b", "succ": "b"}, {"pred": "b", "succ": "a"}]
    s = "baaaaa"
    for k in range(1, 6):
        s2 = derive("baaaaa", rules, k)
        assert s2 == "a" * k + "b" + "a" * (5 - k)
    assert s2 != s


def test_context_skips_branches_and_ignored_symbols():
    # left context of C is A: the side branch [+B] and the turn + are skipped
    assert derive("A[+B]+C", [{"pred": "C", "left": "A", "succ": "D"}], 1, passive="ABD") == "A[+B]+D"
    # right context of A is C, not the B in the branch
    assert derive("A[B]C", [{"pred": "A", "right": "C", "succ": "X"}], 1, passive="BCX") == "X[B]C"
    # a ']' ends the axis: no right context inside a branch's end
    assert derive("[A]C", [{"pred": "A", "right": "C", "succ": "X"}], 1, passive="CX") == "[A]C"
    # contexts bind parameters
    assert derive("B(3)A(1)", [{"pred": "A(x)", "left": "B(y)", "succ": "A(x+y)"}], 1, passive="B") == "B(3)A(4)"


def test_context_rule_takes_precedence_over_context_free():
    rules = [{"pred": "a", "succ": "c"}, {"pred": "a", "left": "b", "succ": "d"}]
    assert derive("ba", rules, 1, passive="bcd") == "bd"
    assert derive("aa", rules, 1, passive="bcd") == "cc"


def test_stochastic_rules_are_seeded_and_follow_p():
    rules = [{"pred": "A", "p": 0.3, "succ": "B"}, {"pred": "A", "p": 0.7, "succ": "C"}]
    s1 = derive("A" * 4000, rules, 1, seed=1, passive="BC")
    assert s1 == derive("A" * 4000, rules, 1, seed=1, passive="BC")
    assert s1 != derive("A" * 4000, rules, 1, seed=2, passive="BC")
    share = s1.count("B") / 4000
    assert abs(share - 0.3) < 0.03


def test_probability_left_over_keeps_the_module():
    s = derive("A" * 4000, [{"pred": "A", "p": 0.25, "succ": "B"}], 1, seed=3, passive="B")
    assert abs(s.count("B") / 4000 - 0.25) < 0.03 and s.count("A") + s.count("B") == 4000


def test_rand_in_expressions_is_seeded():
    a = derive("A", [{"pred": "A", "succ": "F(rand(1, 2))"}], 1, seed=5)
    assert a == derive("A", [{"pred": "A", "succ": "F(rand(1, 2))"}], 1, seed=5)
    assert 1.0 <= float(a[2:-1]) <= 2.0


def test_exploding_string_is_a_clear_error_not_memory_exhaustion():
    t = time.perf_counter()
    with pytest.raises(LSystemSizeError) as e:
        derive("A", ["A=AAAA"], 60, max_modules=50_000)
    assert time.perf_counter() - t < 5
    msg = str(e.value)
    assert "max_modules = 50,000" in msg and "iteration" in msg and "after all 60" in msg
    assert isinstance(e.value, InputError)


@pytest.mark.parametrize("rules, axiom, words", [
    ([{"pred": "A", "succ": "F Q A"}], "A", ["undefined symbol 'Q'", "rules[0]"]),
    ([{"pred": "A", "succ": "F A"}], "A W", ["undefined symbol 'W'", "axiom"]),
    ([{"pred": "A(x)", "succ": "F(y) A(x)"}], "A(1)", ["unknown name 'y'"]),
    ([{"pred": "A(x)", "succ": "A(x, 2)"}], "A(1)", ["given 2 parameter"]),
    ([{"pred": "A", "succ": "F [ A"}], "A", ["unclosed"]),
    ([{"pred": "A", "succ": "F(__import__('os'))"}], "A", ["unsupported"]),
    ([{"pred": "A", "succ": "F((1)"}], "A", ["unclosed"]),
])
def test_bad_rules_are_clear_errors(rules, axiom, words):
    spec = LSystemSpec.model_validate({"axiom": axiom, "rules": rules})
    with pytest.raises(InputError) as e:
        compile_lsystem(spec, "oak")
    assert "species 'oak'" in str(e.value)
    for w in words:
        assert w in str(e.value)


def test_expressions_accept_only_the_whitelist():
    f = compile_expr("max(x, 2) * sin(pi / 2) + (1 if x > 0 else 0)", ["x"])
    assert f({"x": 3.0}, random.Random(0)) == 4.0
    for bad in ("x.__class__", "[1, 2]", "lambda: 1", "open('f')"):
        with pytest.raises(ValueError):
            compile_expr(bad, ["x"])
