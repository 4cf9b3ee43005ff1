"""How carryable is the codebase? The figures issue 36 (a codebase a newcomer can carry) is judged by.

Prints, for the library (kernels/, pipeline/, hardware/, tools/, src/ringscan/):

- each codec's name: the library files outside ``pipeline/codecs/`` and ``kernels/`` that
  name it (bar: <= 1 each; ``registry``-style lookups are what the rest should use);
- modules over 800 lines (bar: none), command modules ``tools/cmd_*.py`` over 400 (bar: none);
- functions over 80 lines or over 8 parameters (the issue: "a reason or a split"), each either
  explained or not: a function whose docstring has a line starting ``Size:`` (a sentence or two on
  why it is this long or takes this many parameters) is explained (bar: none unexplained); the
  largest unexplained of each;
- settings dataclasses and their fields (counted);
- whether ``lint-imports`` keeps every layer contract (bar).

Exit 1 when a bar is missed. Static: reads the source with :mod:`ast`, imports nothing of ringscan.

    python benchmarks/layout_report.py [--list]     # --list: every file/function behind a figure
                                                    # (explained functions marked)
"""

from __future__ import annotations

import argparse
import ast
import re
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LIBRARY = ("kernels", "pipeline", "hardware", "tools", "src/ringscan")
OWN = ("pipeline/codecs/", "kernels/")
MAX_MODULE = 800
MAX_COMMAND = 400
LONG_FUNCTION = 80
MANY_PARAMETERS = 8
# A codec's name as the code spells it: the quoted identifier, or (the single-shot codec,
# whose name "rings" is also a constraint's) its own names.
CODEC_PATTERNS = {
    "gray-rings": r"[\"']gray-rings[\"']",
    "phase-rings": r"[\"']phase-rings[\"']",
    "single-shot rings": r"single[_-]shot|RingsCodec|codec\s*==\s*[\"']rings[\"']",
    "angle code": r"angle_steps|angle_period",
}


def library_files() -> list[Path]:
    out = []
    for top in LIBRARY:
        out += sorted(p for p in (ROOT / top).rglob("*.py") if "__pycache__" not in p.parts)
    return out


def rel(p: Path) -> str:
    return p.relative_to(ROOT).as_posix()


def functions(tree: ast.AST):
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            a = node.args
            params = [x.arg for x in (*a.posonlyargs, *a.args, *a.kwonlyargs) if x.arg not in ("self", "cls")]
            params += [x.arg for x in (a.vararg, a.kwarg) if x is not None]
            yield node, node.end_lineno - node.lineno + 1, len(params)


def explained(node: ast.AST) -> bool:
    """Whether a function's docstring states why it is long or wide: a line starting ``Size:``."""
    doc = ast.get_docstring(node) or ""
    return any(line.strip().startswith("Size:") for line in doc.splitlines())


def oversized(files: list[Path], root: Path = ROOT) -> tuple[list, list]:
    """The functions over ``LONG_FUNCTION`` lines and over ``MANY_PARAMETERS`` parameters in ``files``.

    Two lists, largest first, of ``(size, "path:line name", explained)``; paths relative to ``root``.
    """
    long_fns, wide_fns = [], []
    for f in files:
        tree = ast.parse(f.read_text(encoding="utf-8"), filename=str(f))
        for node, length, params in functions(tree):
            where = f"{f.relative_to(root).as_posix()}:{node.lineno} {node.name}"
            if length > LONG_FUNCTION:
                long_fns.append((length, where, explained(node)))
            if params > MANY_PARAMETERS:
                wide_fns.append((params, where, explained(node)))
    long_fns.sort(key=lambda x: (x[0], x[1]), reverse=True)
    wide_fns.sort(key=lambda x: (x[0], x[1]), reverse=True)
    return long_fns, wide_fns


def is_settings_dataclass(node: ast.ClassDef) -> bool:
    decorated = any("dataclass" in ast.unparse(d) for d in node.decorator_list)
    return decorated and node.name.endswith("Settings")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--list", action="store_true", help="list every file and function behind a figure")
    args = ap.parse_args(argv)
    files = library_files()
    missed = []
    lines = {f: f.read_text(encoding="utf-8").count("\n") + 1 for f in files}
    print(f"library: {len(files)} modules, {sum(lines.values())} lines")

    print("\ncodec names outside pipeline/codecs/ and kernels/ (bar <= 1 file each):")
    for name, pattern in CODEC_PATTERNS.items():
        rx = re.compile(pattern)
        hits = [f for f in files if not rel(f).startswith(OWN) and rx.search(f.read_text(encoding="utf-8"))]
        print(f"  {name}: {len(hits)} files")
        if args.list:
            for f in hits:
                print(f"      {rel(f)}")
        if len(hits) > 1:
            missed.append(f"{name} named in {len(hits)} library files outside codecs/ and kernels/")

    big = sorted(((n, f) for f, n in lines.items() if n > MAX_MODULE), reverse=True)
    cmds = sorted(((n, f) for f, n in lines.items() if f.name.startswith("cmd_") and n > MAX_COMMAND), reverse=True)
    print(f"\nmodules over {MAX_MODULE} lines: {len(big)}; command modules over {MAX_COMMAND}: {len(cmds)}")
    for n, f in big + cmds:
        print(f"  {n:5d}  {rel(f)}")
    if big:
        missed.append(f"{len(big)} modules over {MAX_MODULE} lines")
    if cmds:
        missed.append(f"{len(cmds)} command modules over {MAX_COMMAND} lines")

    settings, fields = 0, 0
    for f in files:
        tree = ast.parse(f.read_text(encoding="utf-8"), filename=str(f))
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef) and is_settings_dataclass(node):
                settings += 1
                fields += sum(isinstance(b, ast.AnnAssign) for b in node.body)
    long_fns, wide_fns = oversized(files)
    long_open = [x for x in long_fns if not x[2]]
    wide_open = [x for x in wide_fns if not x[2]]
    print(f"\nfunctions over {LONG_FUNCTION} lines: {len(long_fns)} ({len(long_fns) - len(long_open)} explained, "
          f"{len(long_open)} not); over {MANY_PARAMETERS} parameters: {len(wide_fns)} "
          f"({len(wide_fns) - len(wide_open)} explained, {len(wide_open)} not); "
          f"each needs a reason (a docstring line 'Size: ...') or a split")
    for length, where, ok in long_fns if args.list else long_open[:5]:
        print(f"  {length:4d} lines  {where}{'  (Size: explained)' if ok else ''}")
    for params, where, ok in wide_fns if args.list else wide_open[:5]:
        print(f"  {params:4d} params {where}{'  (Size: explained)' if ok else ''}")
    if long_open:
        missed.append(f"{len(long_open)} functions over {LONG_FUNCTION} lines with neither a reason nor a split")
    if wide_open:
        missed.append(f"{len(wide_open)} functions over {MANY_PARAMETERS} parameters with neither a reason nor a split")
    print(f"\nsettings dataclasses: {settings}, {fields} fields")

    lint = shutil.which("lint-imports") or str(Path(sys.executable).with_name("lint-imports"))
    if Path(lint).exists():
        r = subprocess.run([lint], cwd=ROOT, capture_output=True, text=True)
        kept = (r.stdout.strip().splitlines() or ["?"])[-1]
        print(f"\nlint-imports: {kept}")
        if r.returncode != 0:
            missed.append("lint-imports breaks a contract")
    else:
        print("\nlint-imports: not installed here (pip install '.[test]')")
        missed.append("lint-imports not run")

    for m in missed:
        print(f"MISSED {m}")
    print("all bars met" if not missed else f"{len(missed)} bar(s) missed")
    return 1 if missed else 0


if __name__ == "__main__":
    sys.exit(main())
