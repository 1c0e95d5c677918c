"""Every OpenCL kernel file of the product has a test that runs on every
device: some test module marked `every_device` (tests/conftest.py) imports a
module that loads the .cl file.

What counts, kept simple: a Python module "loads" a .cl file when its source
names the file (KERNELS = Path(__file__).with_name("kernels.cl")); a test
module is marked when `pytestmark` or one of its tests carries
`every_device`; it exercises the loader when it imports it (at the top or
inside a test, `from pkg import loader` included). Importing is not proof
that each kernel runs, but a file no marked test even imports is certainly
not compared with its reference on every device. bench/ holds measurement
kernels (roofline.cl), not the product's.
"""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PRODUCT = ("pipeline", "worldlib", "stages")


def kernel_files() -> list[Path]:
    return sorted(p for top in PRODUCT for p in (ROOT / top).rglob("*.cl"))


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def loaders(cl_file: Path) -> set[str]:
    """Modules beside the .cl file (its package) whose source names it."""
    return {module_name(py) for py in cl_file.parent.glob("*.py") if f'"{cl_file.name}"' in py.read_text()}


def _marked(tree: ast.Module) -> bool:
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign) and any(getattr(t, "id", "") == "pytestmark" for t in node.targets):
            if "every_device" in ast.unparse(node.value):
                return True
        if isinstance(node, ast.FunctionDef) and any("every_device" in ast.unparse(d) for d in node.decorator_list):
            return True
    return False


def _imports(tree: ast.Module, module: str) -> set[str]:
    """Every module (and `package.name` of a from-import) the test imports."""
    package = module.rsplit(".", 1)[0]
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[:len(package.split(".")) - node.level + 1] + ([base] if base else []))
            out.add(base)
            out.update(f"{base}.{a.name}" for a in node.names)
    return out


def marked_test_imports() -> dict[str, set[str]]:
    out = {}
    for test in sorted((ROOT / "tests").rglob("test_*.py")):
        tree = ast.parse(test.read_text())
        if _marked(tree):
            out[module_name(test)] = _imports(tree, module_name(test))
    return out


def test_every_kernel_file_is_exercised_by_an_every_device_test():
    files = kernel_files()
    assert len(files) >= 10, [str(f) for f in files]  # the finder itself works
    tests = marked_test_imports()
    missing = []
    for cl_file in files:
        names = loaders(cl_file)
        assert names, f"no module beside {cl_file.relative_to(ROOT)} loads it"
        if not any(names & imported for imported in tests.values()):
            missing.append(f"{cl_file.relative_to(ROOT)} (loaded by {sorted(names)})")
    assert not missing, f"kernel files no every_device test imports the loader of: {missing}"


def test_the_check_sees_a_file_nobody_tests(tmp_path):
    """The finder's own honesty: a marked test importing an unrelated module does not count."""
    tree = ast.parse("import pytest\npytestmark = pytest.mark.every_device\nfrom stages.heightmap import noise\n")
    assert _marked(tree)
    imported = _imports(tree, "tests.stages.x.test_y")
    assert "stages.heightmap.noise" in imported
    assert not loaders(ROOT / "stages" / "erosion" / "kernels.cl") & imported
    assert not _marked(ast.parse("import pytest\n\ndef test_a():\n    pass\n"))
