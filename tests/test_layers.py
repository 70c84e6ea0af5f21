"""The layer table in the README is the law: every module's imports are read (ast, including
imports inside functions) and checked against it, so a shortcut across layers fails here
rather than in a reviewer's head."""

import ast
import re
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
ROW = re.compile(r"^\| `(\w+)/` \| .* \| ([^|]+) \|$")


def layer_rules(readme: str) -> dict[str, set[str] | None]:
    """{layer: the layers it may import} from the README's Layout table; None = everything."""
    rules: dict[str, set[str] | None] = {}
    table = readme.split("## Layout", 1)[1].split("\n## ", 1)[0]
    for line in table.splitlines():
        match = ROW.match(line.strip())
        if not match:
            continue
        layer, allowed = match.group(1), match.group(2).strip()
        if allowed == "everything":
            rules[layer] = None
        elif allowed == "nothing of ours":
            rules[layer] = set()
        else:
            rules[layer] = {name.strip().strip("`") for name in allowed.split(",")}
    return rules


def imported_packages(source: str, module: str) -> set[str]:
    """The top-level packages a module's source imports, relative imports resolved against
    the dotted `module` name."""
    out = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                out.add(module.split(".")[0])
            elif node.module:
                out.add(node.module.split(".")[0])
    return out


def forbidden_imports(layer: str, module: str, source: str,
                      rules: dict[str, set[str] | None]) -> set[str]:
    """The layers of ours that `module` (in `layer`) imports although the rules forbid it."""
    allowed = rules[layer]
    ours = set(rules)
    imported = imported_packages(source, module) & ours - {layer}
    if allowed is None:
        return set()
    return imported - allowed


def modules(folder: Path):
    for path in sorted(folder.rglob("*.py")):
        if path.name.endswith("_pb2.py"):
            continue
        yield path, ".".join(path.relative_to(ROOT).with_suffix("").parts)


RULES = layer_rules(README.read_text())


def test_the_readme_table_names_every_package_and_its_rule():
    packages = {p.parent.name for p in ROOT.glob("*/__init__.py")}
    assert set(RULES) == packages, "README Layout table and the packages differ"
    assert RULES["protocol"] == set() and RULES["model"] == set()
    assert RULES["dashboard"] == {"protocol"}
    assert RULES["commands"] is None
    # the robot and its wiring sit below the commands, above every layer a robot is made of
    assert RULES["robot"] == {"protocol", "model", "driver", "sim_bus", "controller"}
    # nothing below the commands may import them
    assert all(rule is None or "commands" not in rule for rule in RULES.values())


def test_pyproject_packages_every_package_folder():
    """A package left out of the list is missing from a wheel (an editable install hides it)."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    folders = {".".join(p.parent.relative_to(ROOT).parts) for p in ROOT.glob("*/**/__init__.py")
               if p.parent.parts[len(ROOT.parts)] not in ("tests", "docs", "examples")}
    assert set(project["tool"]["setuptools"]["packages"]) == folders


def test_only_the_robot_layer_puts_a_virtual_drive_behind_a_master():
    """The wiring of a robot is a library layer: a command hands typed values to `robot/`,
    which alone links a master to an embedded virtual drive (tests may too)."""
    linkers = {"EmbeddedDrive", "EmbeddedBus"}
    offences = []
    for layer in sorted(set(RULES) - {"robot", "sim_bus"}):
        for path, module in modules(ROOT / layer):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.ImportFrom) and node.module == "sim_bus.embedded":
                    offences += [f"{module} imports {alias.name}" for alias in node.names
                                 if alias.name in linkers]
    assert not offences, offences


@pytest.mark.parametrize("layer", sorted(RULES))
def test_each_layer_imports_only_what_the_table_allows(layer):
    offences = []
    for path, module in modules(ROOT / layer):
        bad = forbidden_imports(layer, module, path.read_text(), RULES)
        offences += [f"{module} imports {name}" for name in sorted(bad)]
    assert not offences, offences


def test_scripts_outside_the_layers_do_not_import_commands():
    for folder in ("docs", "examples"):
        for path, module in modules(ROOT / folder):
            assert "commands" not in imported_packages(path.read_text(), module), module


def test_every_console_script_points_into_commands():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())
    scripts = project["project"]["scripts"]
    assert scripts
    for name, target in scripts.items():
        assert target.startswith("commands."), f"{name} = {target}"
        module = ROOT / (target.split(":")[0].replace(".", "/") + ".py")
        assert module.is_file(), f"{name}: {module} missing"
    assert "commands" in project["tool"]["setuptools"]["packages"]


def test_the_checker_catches_a_forbidden_import():
    rules = {"protocol": set(), "model": set(), "controller": {"protocol", "model", "driver"},
             "driver": {"protocol"}, "sim_bus": {"protocol", "model"}, "commands": None}
    lazy = "def f():\n    from sim_bus.embedded import EmbeddedDrive\n    return EmbeddedDrive\n"
    assert forbidden_imports("controller", "commands.actuatord", lazy, rules) == {"sim_bus"}
    assert forbidden_imports("model", "model.x", "import controller.mpc\n", rules) == {
        "controller"}
    assert forbidden_imports("driver", "driver.x", "from commands import options\n",
                             rules) == {"commands"}
    assert forbidden_imports("driver", "driver.x", "from . import interface\n", rules) == set()
    assert forbidden_imports("commands", "commands.x", "import sim_bus, controller\n",
                             rules) == set()
    assert forbidden_imports("controller", "controller.x", "import numpy, model.dynamics\n",
                             rules) == set()


def test_the_table_parser_reads_the_rules():
    readme = ("## Layout\n\n| folder | owns | may import |\n|---|---|---|\n"
              "| `protocol/` | wire | nothing of ours |\n"
              "| `driver/` | master | `protocol` |\n"
              "| `commands/` | scripts | everything |\n\n## Next\n| `x/` | y | `z` |\n")
    assert layer_rules(readme) == {"protocol": set(), "driver": {"protocol"}, "commands": None}
