"""The library reports through `logging`, never by printing: no function takes `print` as a default
logger, and no module outside the command-line front ends calls print()."""

import ast
import pathlib

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGES = ("splatsearch", "kernels", "nav", "social")
FRONT_ENDS = {"cli.py"}  # argparse front ends may print their one-line answers


def _modules():
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            if path.name not in FRONT_ENDS:
                yield path, ast.parse(path.read_text(), str(path))


def test_no_print_defaults_and_no_print_calls():
    found = []
    for path, tree in _modules():
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                defaults = node.args.defaults + [d for d in node.args.kw_defaults if d is not None]
                found += [f"{path.relative_to(ROOT)}:{node.lineno} default print" for d in defaults
                          if isinstance(d, ast.Name) and d.id == "print"]
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "print":
                found.append(f"{path.relative_to(ROOT)}:{node.lineno} print()")
    assert found == []
