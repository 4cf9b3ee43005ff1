"""Figures a command printed, read back as numbers.

A test compares a printed figure with its truth as a number within a tolerance that says
why it is that size, never as text: OpenCV's threads and the BLAS may move a fit's last
digits from one machine to the next, and a figure printed to one decimal then reads
1876.6 on one machine and 1876.7 on another.
"""

from __future__ import annotations

import re

NUMBER = r"[-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?"


def _pattern(template: str) -> str:
    """``template`` as a regular expression: its text literal (a run of whitespace matches any
    run), a group capturing a number at each ``{}``."""

    def literal(part: str) -> str:
        core = r"\s+".join(re.escape(w) for w in part.split())
        if not core:
            return r"\s+" if part else ""
        return (r"\s+" if part[0].isspace() else "") + core + (r"\s+" if part[-1].isspace() else "")

    return f"({NUMBER})".join(literal(p) for p in template.split("{}"))


def _match(text: str, template: str) -> re.Match:
    m = re.search(_pattern(template), text)
    if m is None:  # an AssertionError (not pytest.fail): benchmarks/ scripts use these helpers too
        raise AssertionError(f"nothing matches {template!r} in:\n{text}")
    return m


def printed_figures(text: str, template: str) -> tuple[float, ...]:
    """The numbers standing at the ``{}`` of ``template`` in the first place of ``text`` it matches.

    ``template`` is literal text with ``{}`` where a number stands, e.g.
    ``"projector: RMS reprojection error {} px"``. Raises AssertionError, naming the template, when
    nothing in ``text`` matches it.
    """
    return tuple(float(g) for g in _match(text, template).groups())


def printed_figure(text: str, template: str) -> float:
    """The one number of ``template`` (one ``{}``) in ``text``: :func:`printed_figures`."""
    (value,) = printed_figures(text, template)
    return value


def rounding(decimals: int) -> float:
    """Half a unit of the last printed decimal: what printing alone may have moved a figure by."""
    return 0.5 * 10.0 ** -decimals


def assert_figures_as_quoted(text: str, quoted: str, template: str, *, rtol: float, why: str) -> None:
    """The figures of ``template`` that ``text`` printed agree with the ones ``quoted`` (a doc's
    copy of the same output): each within ``rtol`` of its value (``why`` says where that much may
    come from) plus half a unit of the quoted figure's last decimal (the printing)."""
    got = printed_figures(text, template)
    for g, q in zip(got, _match(quoted, template).groups()):
        decimals = len(q.split(".")[1]) if "." in q else 0
        tol = rtol * abs(float(q)) + rounding(decimals)
        assert abs(g - float(q)) <= tol, f"{template!r}: printed {g}, quoted {q} (tolerance {tol:.3g}: {why})"
