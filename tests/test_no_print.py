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


def _environ_writes(node) -> bool:
    """``os.environ[...] = ...``, ``os.environ.setdefault/update(...)`` or ``os.putenv(...)``."""
    if isinstance(node, ast.Assign):
        t = node.targets[0]
        return isinstance(t, ast.Subscript) and ast.unparse(t.value) == "os.environ"
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
        owner = ast.unparse(node.func.value)
        return (owner == "os.environ" and node.func.attr in ("setdefault", "update")) or \
            (owner == "os" and node.func.attr == "putenv")
    return False


def test_the_library_does_not_write_the_users_environment():
    """Settings are arguments; nothing sets os.environ except a worker process giving XLA its
    thread count (splatsearch.parallel.limit_threads, in its own spawned process)."""
    allowed = {("splatsearch/parallel.py", "limit_threads")}
    found = set()
    for path, tree in _modules():
        rel = str(path.relative_to(ROOT))
        scopes = [(n.name, n) for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]
        scopes += [("<module>", s) for s in tree.body if not isinstance(s, (ast.FunctionDef, ast.ClassDef))]
        for name, scope in scopes:
            if (rel, name) in allowed:
                continue
            found |= {f"{rel}:{n.lineno} in {name}" for n in ast.walk(scope) if _environ_writes(n)}
    assert sorted(found) == []
