"""The compiled CSV number formatting (:mod:`flexforce.datasets.io.csvformat`)."""

from __future__ import annotations

import numpy as np

from flexforce.datasets.io.csvformat import DIGITS, format_rows


def test_values_read_back_within_the_stated_precision():
    rng = np.random.default_rng(3)
    vals = rng.standard_normal(20000) * 10.0 ** rng.integers(-30, 30, 20000)
    vals = np.concatenate([vals, [1.0, 0.1, 9.999999999999999e15, 1e16, 1e-4, 9.9999999999999995e-5, 5e-324,
                                  123456789012345678.0, 0.5 - 2.0 ** -53, 99999999999999.99]])
    back = np.array([float(x) for x in format_rows(vals[:, None]).split()])
    rel = np.abs(back - vals) / np.abs(vals)
    # 15 significant digits: half a unit of the 15th is 5e-15 of a value starting with 1; one
    # unit off (the float scaling) at most 1e-14 -- measured 5.1e-15 on these
    assert np.max(rel[:-4]) <= 1e-14
    assert np.max(rel[-4:]) <= 1e-14 or back[-4] == vals[-4]  # the subnormal may round anyhow


def test_layout_is_that_of_repr_for_short_values():
    vals = [0.0, -0.0, 1.0, 0.1, -2.5, 3600.005, 1e16, 1e-5, 1.5e-7, 0.0001, 123.456, 1e15, 2.0e22, -7.25e-300]
    lines = format_rows(np.array(vals)[:, None]).splitlines()
    assert lines == [repr(v) for v in vals]


def test_special_values_and_exact_integers():
    t_ns = np.array([1_700_000_000_000_000_001, -5, 0], dtype=np.int64)
    table = np.array([[np.nan, 0.0, np.inf], [-np.inf, 0.0, 1.0], [2.0, 0.0, -1.0]])
    text = format_rows(table, t_ns, int_col=1)
    assert text == "nan,1700000000000000001,inf\n-inf,-5,1.0\n2.0,0,-1.0\n"
    table = np.loadtxt(text.splitlines(), delimiter=",")
    assert np.isnan(table[0, 0]) and table[0, 2] == np.inf and table[1, 0] == -np.inf


def test_digits_of_a_long_value():
    text = format_rows(np.array([[np.pi, -np.e * 1e-9]]))
    a, b = text.strip().split(",")
    assert a == "3.14159265358979" and len(a.replace(".", "")) == DIGITS
    assert b == "-2.71828182845905e-09"
