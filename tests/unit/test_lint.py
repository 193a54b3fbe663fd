"""The house lint and type rules hold over the whole tree.

ruff (pyproject [tool.ruff]) checks every Python file; mypy (pyproject [tool.mypy], strict)
checks the library packages it lists under ``files``; and no public function of those
packages is annotated ``-> Any``.
"""

import ast
import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
LIBRARY_PACKAGES = ("flightkit", "trajectories", "capture", "estimation")

# Public functions that may say ``-> Any``, with the reason.
ANY_RETURN_ALLOWED = {
    # The overload for a required key: a dataclass field specifier with no default has no
    # type of its own (as dataclasses.field); the field's annotation gives it.
    ("flightkit/settings.py", "setting"),
}


def test_ruff_is_clean() -> None:
    ruff = shutil.which("ruff", path=str(Path(sys.executable).parent)) or shutil.which("ruff")
    if ruff is None:
        pytest.skip("ruff is not installed (it comes with the [test] extra)")
    r = subprocess.run(
        [ruff, "check", "--output-format", "concise", "flightkit", "trajectories", "capture", "estimation",
         "tests", "bench", "examples"],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-2000:]


def test_mypy_is_clean() -> None:
    """mypy --strict over the packages of [tool.mypy] ``files``; the cache in the repo's
    (git-ignored) .mypy_cache keeps a rerun to a few seconds."""
    if importlib.util.find_spec("mypy") is None:
        pytest.skip("mypy is not installed (it comes with the [test] extra)")
    r = subprocess.run(
        [sys.executable, "-m", "mypy", "--cache-dir", str(ROOT / ".mypy_cache")],
        cwd=ROOT, capture_output=True, text=True, timeout=600,
    )
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-2000:]


def _returns_any(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    node = fn.returns
    if isinstance(node, ast.Constant) and isinstance(node.value, str):  # a string annotation
        node = ast.parse(node.value, mode="eval").body
    return (isinstance(node, ast.Name) and node.id == "Any") or (
        isinstance(node, ast.Attribute) and node.attr == "Any"
    )


def _is_overload(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    return any(
        (isinstance(d, ast.Name) and d.id == "overload") or (isinstance(d, ast.Attribute) and d.attr == "overload")
        for d in fn.decorator_list
    )


def _public_any_returns(body: list[ast.stmt], prefix: str) -> list[tuple[str, int]]:
    """``(qualified name, line)`` of the public functions and methods in ``body`` that return
    ``Any``. The implementation of an overloaded function is skipped: callers see its overloads."""
    overloaded = {
        n.name for n in body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)) and _is_overload(n)
    }
    found: list[tuple[str, int]] = []
    for node in body:
        if isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
            found += _public_any_returns(node.body, f"{prefix}{node.name}.")
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and not node.name.startswith("_"):
            if node.name in overloaded and not _is_overload(node):
                continue
            if _returns_any(node):
                found.append((prefix + node.name, node.lineno))
    return found


def test_no_public_function_returns_any() -> None:
    offenders = []
    for package in LIBRARY_PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            tree = ast.parse(path.read_text(encoding="utf-8"), filename=rel)
            for name, line in _public_any_returns(tree.body, ""):
                if (rel, name) not in ANY_RETURN_ALLOWED:
                    offenders.append(f"{rel}:{line}: {name}")
    assert not offenders, (
        "public functions annotated -> Any (give them a real type: a concrete class, a Protocol, "
        "a TypedDict; TYPE_CHECKING imports for heavy modules):\n" + "\n".join(offenders)
    )


def test_the_any_scan_finds_what_it_should() -> None:
    src = (
        "from typing import Any, overload\n"
        "def a() -> Any: ...\n"
        "def _b() -> Any: ...\n"
        "class C:\n"
        "    def m(self) -> 'Any': ...\n"
        "    async def n(self) -> typing.Any: ...\n"
        "    def ok(self) -> int: ...\n"
        "class _D:\n"
        "    def m(self) -> Any: ...\n"
        "@overload\n"
        "def f(x: int) -> int: ...\n"
        "@overload\n"
        "def f(x: str) -> str: ...\n"
        "def f(x: Any) -> Any: ...\n"
    )
    assert _public_any_returns(ast.parse(src).body, "") == [("a", 2), ("C.m", 5), ("C.n", 6)]
