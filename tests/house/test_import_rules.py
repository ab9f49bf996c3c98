"""The house rules, read from the import graph of parjam/ (and of tests/ and scripts/ for private
names): they fail when a change breaks one.

1. Physics knows no files: parjam.pack, .net, .vib, .softmodes and .lengths import nothing from
   parjam.files, the command line, parjam.study or parjam.plot, nor h5py or matplotlib (at module
   level or inside functions).
2. parjam.files computes no physics: from the physics packages it imports only the data model and
   the row layout (ALLOWED_IN_FILES).
3. Only the command line draws: nothing outside parjam.commands and parjam.plot imports
   parjam.plot (the study runner included).
4. No import cycles among parjam's modules (module-level imports).
5. No private name crosses a module: no ``from parjam... import _name`` and no ``module._name``
   of a parjam module, in parjam/, tests/ or scripts/.
"""

import ast
import os

from conftest import ROOT

PHYSICS = ("parjam.pack", "parjam.net", "parjam.vib", "parjam.softmodes", "parjam.lengths")
NOT_IN_PHYSICS = ("parjam.files", "parjam.commands", "parjam.cli", "parjam.study", "parjam.plot",
                  "h5py", "matplotlib")
# what parjam.files may take from the physics packages: the data model and the row layout
ALLOWED_IN_FILES = {
    ("parjam.net.system", "Packing"), ("parjam.net.system", "wrap"),
    ("parjam.net.system", "DUPLICATE_TOL"),
    ("parjam.net.system", "coinciding_pairs"),
    ("parjam.net.system", "sphere_volume"),  # a particle's volume, for the exports' mass density
    ("parjam.net.active", "row_block"), ("parjam.net.active", "home_rows"),
    ("parjam.net.domain", "as_mpi"), ("parjam.net.domain", "blocks_in_turn"),
    ("parjam.pack.minimize", "FireState"), ("parjam.pack.minimize", "MinimiseState"),
    ("parjam.pack.minimize", "MinResult"),
}


def module_name(path):
    rel = os.path.relpath(path, ROOT)[:-3].replace(os.sep, ".")
    return rel[:-len(".__init__")] if rel.endswith(".__init__") else rel


def python_files(*tops):
    for top in tops:
        for folder, _, files in os.walk(os.path.join(ROOT, top)):
            for name in sorted(files):
                if name.endswith(".py"):
                    yield os.path.join(folder, name)


def parse(path):
    with open(path) as f:
        return ast.parse(f.read(), path)


def imports(tree, top_level_only=False):
    """(module, name or None, line) of every import; ``name`` for ``from M import name``."""
    nodes = tree.body if top_level_only else ast.walk(tree)
    for node in nodes:
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name, None, node.lineno
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            for a in node.names:
                yield node.module, a.name, node.lineno


def under(module, prefixes):
    return any(module == p or module.startswith(p + ".") for p in prefixes)


MODULES = {module_name(p): p for p in python_files("parjam")}


def resolved(module, name):
    """The module an import binds: ``from parjam.x import y`` is parjam.x.y when that is a
    module, else parjam.x."""
    if name and f"{module}.{name}" in MODULES:
        return f"{module}.{name}"
    return module


def test_physics_imports_no_files_cli_study_or_plot():
    bad = []
    for mod, path in MODULES.items():
        if not under(mod, PHYSICS):
            continue
        for module, name, line in imports(parse(path)):
            target = resolved(module, name)
            if under(target, NOT_IN_PHYSICS):
                bad.append(f"{os.path.relpath(path, ROOT)}:{line} imports {target}")
    assert not bad, "physics must not know files, the CLI, studies or plots:\n" + "\n".join(bad)


def test_files_take_only_the_data_model_from_physics():
    bad = []
    for mod, path in MODULES.items():
        if not under(mod, ("parjam.files",)):
            continue
        for module, name, line in imports(parse(path)):
            target = resolved(module, name)
            if under(target, PHYSICS) and (module, name) not in ALLOWED_IN_FILES:
                bad.append(f"{os.path.relpath(path, ROOT)}:{line} imports "
                           f"{module}{'.' + name if name else ''}")
    assert not bad, "parjam.files computes no physics:\n" + "\n".join(bad)


def test_only_the_command_line_draws():
    bad = []
    for mod, path in MODULES.items():
        if under(mod, ("parjam.commands", "parjam.plot")):
            continue
        for module, name, line in imports(parse(path)):
            if under(resolved(module, name), ("parjam.plot", "matplotlib")):
                bad.append(f"{os.path.relpath(path, ROOT)}:{line} imports {module}")
    assert not bad, "only parjam.commands and parjam.plot draw:\n" + "\n".join(bad)


def module_graph():
    graph = {}
    for mod, path in MODULES.items():
        deps = set()
        for module, name, _ in imports(parse(path), top_level_only=True):
            target = resolved(module, name)
            if target in MODULES and target != mod:
                deps.add(target)
        graph[mod] = deps
    return graph


def test_no_import_cycles():
    graph = module_graph()
    state, cycles = {}, []

    def visit(node, stack):
        state[node] = "open"
        for nxt in sorted(graph[node]):
            if state.get(nxt) == "open":
                cycles.append(" -> ".join(stack[stack.index(nxt):] + [nxt]))
            elif nxt not in state:
                visit(nxt, stack + [nxt])
        state[node] = "done"

    for node in sorted(graph):
        if node not in state:
            visit(node, [node])
    # a package importing its own submodules in __init__ is not a cycle of concepts
    cycles = [c for c in cycles if not all(m.startswith(c.split(" -> ")[0].rsplit(".", 1)[0])
                                           for m in c.split(" -> "))]
    assert not cycles, "import cycles:\n" + "\n".join(cycles)


def private_uses(path):
    """``from parjam... import _x`` and ``mod._x`` where ``mod`` is a parjam module bound by an
    import of this file."""
    tree = parse(path)
    bound, found = set(), []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("parjam"):
            for a in node.names:
                if a.name.startswith("_") and not a.name.startswith("__"):
                    found.append((node.lineno, f"{node.module}.{a.name}"))
                if f"{node.module}.{a.name}" in MODULES:
                    bound.add(a.asname or a.name)
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("parjam") and a.asname:
                    bound.add(a.asname)
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                and node.value.id in bound and node.attr.startswith("_")
                and not node.attr.startswith("__")):
            found.append((node.lineno, f"{node.value.id}.{node.attr}"))
    return found


# private attributes of other libraries that are their documented API
PUBLIC_UNDERSCORE = {"_exit"}  # os._exit: leave at once from a signal handler


def foreign_private_attributes(path):
    """``obj._x`` where ``obj`` is not ``self``/``cls`` and nothing in this file defines ``_x``:
    another module's private attribute (``ff._rebuild`` on a ForceField made elsewhere)."""
    tree = parse(path)
    defined = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            defined.add(node.name)
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
            defined.add(node.attr)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            defined.add(node.id)
    found = []
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and node.attr.startswith("_")
                and not node.attr.startswith("__") and node.attr not in defined
                and node.attr not in PUBLIC_UNDERSCORE
                and not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"))):
            found.append((node.lineno, f".{node.attr}"))
    return found


def test_no_private_names_across_modules():
    bad = []
    for path in python_files("parjam", "tests", "scripts"):
        for line, what in private_uses(path) + foreign_private_attributes(path):
            bad.append(f"{os.path.relpath(path, ROOT)}:{line} uses {what}")
    assert not bad, "private names used across modules:\n" + "\n".join(bad)


def test_the_rules_see_a_violation(tmp_path):
    """The checks are not vacuous: a physics module importing h5py and a private name are
    found."""
    src = tmp_path / "bad.py"
    src.write_text("import h5py\nfrom parjam.pack import fire\nfire._x\n"
                   "from parjam.net.system import _private\nff = fire.make()\nff._rebuild()\n")
    tree = parse(str(src))
    assert ("h5py", None, 1) in list(imports(tree))
    assert "parjam.pack.fire" in MODULES
    assert [w for _, w in private_uses(str(src))] == ["parjam.net.system._private", "fire._x"]
    assert sorted(w for _, w in foreign_private_attributes(str(src))) == ["._rebuild", "._x"]
