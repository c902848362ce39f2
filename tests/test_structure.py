"""The package's shape (its modules import downwards, never in a circle): no import cycle inside
``twinrl/``, no module reaching into another's private names, and ``loop.run`` a short walk over its
stages.

How it checks, without importing anything: every ``twinrl/**/*.py`` is parsed with ``ast`` and every
import statement in it counts, at module level or inside a function (a lazy import is still a
dependency). ``from twinrl.a import b`` is an edge to ``twinrl.a.b`` when that is a module, else to
``twinrl.a``; a dotted use ``twinrl.a.b.f`` after ``import twinrl`` (PEP 562 lazy attributes) and a
string constant that names a module exactly (``importlib.import_module`` tables) are edges too. The
implicit import of a module's parent package is not an edge (every submodule would otherwise form a
cycle with a package ``__init__`` that re-exports it). Cycles are the strongly connected components
of that graph with more than one module.

A private name is one with a single leading underscore. Importing one from another module
(``from twinrl.x import _f``) or reading one off a module (``x._f`` where ``x`` is bound to a
``twinrl`` module) counts; a private *module* (``twinrl.render._raymath``) may be imported anywhere in
the package that holds it.
"""

from __future__ import annotations

import ast
import pathlib

import twinrl

ROOT = pathlib.Path(twinrl.__file__).parent


def _modules() -> dict[str, pathlib.Path]:
    mods = {}
    for path in ROOT.rglob("*.py"):
        parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        mods[".".join(parts)] = path
    return mods


MODULES = _modules()


def _owner(dotted: str) -> str | None:
    """The longest prefix of ``dotted`` that is a module of the package."""
    while dotted and dotted not in MODULES:
        dotted = dotted.rpartition(".")[0]
    return dotted or None


def _is_private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def _private_module_outside(module: str, importer: str | None) -> bool:
    """Whether ``importer`` (a module of the package, or ``None`` for a file outside it: a test,
    a benchmark) may not import ``module``: a private module (``twinrl.render._pack``) belongs to
    the package that holds it."""
    parts = module.split(".")
    for i, part in enumerate(parts):
        if _is_private(part):
            holder = ".".join(parts[:i])
            return importer is None or not (importer == holder
                                            or importer.startswith(holder + "."))
    return False


def _scan(name: str, source: str | None = None) -> tuple[set[str], list[str]]:
    """(modules ``name`` depends on, the private names of other modules it uses); ``source``
    replaces the module's file (for testing the checker)."""
    path = MODULES[name]
    tree = ast.parse(path.read_text() if source is None else source, filename=str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    return _scan_tree(tree, name, package)


def _scan_file(path: pathlib.Path) -> list[str]:
    """The private names of ``twinrl`` a file outside the package (a test, a benchmark) uses."""
    return _scan_tree(ast.parse(path.read_text(), filename=str(path)), None, "")[1]


def _scan_tree(tree: ast.AST, name: str | None, package: str) -> tuple[set[str], list[str]]:
    deps: set[str] = set()
    private: list[str] = []
    aliases: dict[str, str] = {}  # local name -> twinrl module it is bound to
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] == "twinrl" and (t := _owner(a.name)):
                    deps.add(t)
                    if _private_module_outside(t, name):
                        private.append(f"import {a.name}")
                    if a.asname:
                        aliases[a.asname] = t
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[:len(package.split(".")) - (node.level - 1)]
                base = ".".join(up + ([base] if base else []))
            if base.split(".")[0] != "twinrl":
                continue
            for a in node.names:
                full = f"{base}.{a.name}"
                if full in MODULES:
                    deps.add(full)
                    aliases[a.asname or a.name] = full
                    if _private_module_outside(full, name):
                        private.append(f"from {base} import {a.name}")
                else:
                    deps.add(_owner(base))
                    if _private_module_outside(_owner(base) or "", name):
                        private.append(f"from {base} import {a.name}")
                        continue
                    if _is_private(a.name) and _owner(base) != name:
                        private.append(f"from {base} import {a.name}")
        elif isinstance(node, ast.Attribute):
            chain, value = [node.attr], node.value
            while isinstance(value, ast.Attribute):
                chain.append(value.attr)
                value = value.value
            if not isinstance(value, ast.Name):
                continue
            chain.reverse()
            head = "twinrl" if value.id == "twinrl" else aliases.get(value.id)
            if head is None:
                continue
            dotted = ".".join([head] + chain)
            owner = _owner(dotted)
            if owner not in (None, "twinrl"):
                deps.add(owner)
            attr = dotted[len(owner) + 1:].split(".")[0] if owner and dotted != owner else ""
            if _is_private(attr) and owner != name and f"{owner}.{attr}" not in MODULES:
                private.append(f"{owner}.{attr}")
        elif (isinstance(node, ast.Constant) and isinstance(node.value, str)
              and node.value in MODULES and node.value != "twinrl"
              and not (name or "").startswith(node.value + ".")):
            # a string naming a package that holds this module is a name (a format's, a
            # logger's), not a lazy import of it: the module is already inside it
            deps.add(node.value)
    deps.discard(name)
    deps.discard(None)
    return deps, private


GRAPH = {name: _scan(name) for name in MODULES}


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    for start in edges:
        if start in index:
            continue
        work = [(start, iter(sorted(edges[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(edges.get(w, ())))))
                    break
                if w in on_stack:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        found.append(sorted(comp))
    return found


def test_the_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_the_graph_sees_lazy_and_function_level_imports():
    # twinrl.eval imports envs inside a function; twinrl.real lazily, through a table: both count
    assert "twinrl.envs" in GRAPH["twinrl.eval"][0]
    assert "twinrl.real.twin" in GRAPH["twinrl.real"][0]  # a string in its lazy table


def test_the_private_name_finder_finds_private_names():
    source = ("from twinrl.learn.pods import _build, PODSConfig\n"
              "def f():\n"
              "    from twinrl.learn import pods\n"
              "    import twinrl\n"
              "    return pods._compile_key, twinrl.learn.trajopt._x, pods.__name__\n")
    deps, private = _scan("twinrl.loop", source)
    assert private == ["from twinrl.learn.pods import _build", "twinrl.learn.pods._compile_key",
                       "twinrl.learn.trajopt._x"]
    assert {"twinrl.learn.pods", "twinrl.learn.trajopt"} <= deps


def test_no_import_cycles_inside_the_package():
    edges = {name: deps for name, (deps, _) in GRAPH.items()}
    cycles = _cycles(edges)
    detail = ["  " + " ; ".join(f"{m} -> {sorted(edges[m] & set(c))}" for m in c)
              for c in cycles]
    assert not cycles, "import cycles:\n" + "\n".join(detail)


def test_no_module_imports_another_modules_private_names():
    used = {name: private for name, (_, private) in GRAPH.items() if private}
    assert not used, f"private names used across modules: {used}"


def test_the_private_name_finder_sees_tests_and_private_modules(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text("from twinrl.real.dataset import _format\n"
                     "from twinrl.learn.runner import _figures, train_run\n"
                     "import twinrl.learn.runner as runner\n"
                     "x = runner._y\n")
    assert _scan_file(probe) == ["from twinrl.real.dataset import _format",
                                 "from twinrl.learn.runner import _figures", "twinrl.learn.runner._y"]
    # inside the package a private module belongs to the package that holds it
    assert not _private_module_outside("twinrl.real.dataset._format", "twinrl.real.dataset.reader")
    assert not _private_module_outside("twinrl.render._pack", "twinrl.render.renderer")
    assert _private_module_outside("twinrl.render._pack", "twinrl.envs.base")


OUTSIDE = sorted([*(ROOT.parent / "tests").rglob("*.py"), *(ROOT.parent / "bench").rglob("*.py"),
                  *(ROOT.parent / "examples").rglob("*.py")])


def test_no_test_bench_or_example_imports_private_names():
    # what a user cannot rely on, the tests and benchmarks do not either: a test of a private
    # helper is a test of an implementation detail that a refactor silently breaks
    used = {}
    for path in OUTSIDE:
        if path.name != "test_structure.py" and (private := _scan_file(path)):
            used[str(path.relative_to(ROOT.parent))] = private
    assert OUTSIDE and not used, f"private names of twinrl used outside the package: {used}"


MAX_MODULE_LINES = 600


def test_no_module_is_over_600_lines():
    # a module over ~600 lines mixes concerns (split by concern, not in halves)
    long = {name: n for name, path in MODULES.items()
            if (n := len(path.read_text().splitlines())) > MAX_MODULE_LINES}
    assert not long, f"modules over {MAX_MODULE_LINES} lines: {long}"


# The layers, lowest first (docs/architecture.md). A module may import its own layer and the ones
# below, never one above. The base layer holds what every layer uses: the package itself (its lazy
# attribute table), the JAX settings and the writers of results (``report``: JSON, tables, plots).
LAYERS = (
    ("twinrl", "twinrl.jaxconfig", "twinrl.report", "twinrl.progress"),
    ("twinrl.physics",),
    ("twinrl.render",),
    ("twinrl.envs",),
    ("twinrl.real",),
    ("twinrl.real2sim",),
    ("twinrl.learn",),
    ("twinrl.sim2real",),
    ("twinrl.eval", "twinrl.sense"),
    ("twinrl.loop",),
    ("twinrl.cli",),
)


def _layer(module: str) -> int:
    """Index in ``LAYERS`` of the longest entry that is ``module`` or a package holding it."""
    best, length = None, -1
    for i, layer in enumerate(LAYERS):
        for entry in layer:
            if (module == entry or module.startswith(entry + ".")) and len(entry) > length:
                best, length = i, len(entry)
    assert best is not None, f"{module} is in no layer: add it to LAYERS"
    return best


def _upward(edges: dict[str, set[str]]) -> list[str]:
    return sorted(f"{m} -> {d}" for m, deps in edges.items() for d in deps
                  if _layer(d) > _layer(m))


def test_the_layer_check_finds_an_upward_import():
    assert _upward({"twinrl.physics.chain": {"twinrl.render.camera", "twinrl.physics.sim"},
                    "twinrl.cli.run": {"twinrl.loop"}}) == ["twinrl.physics.chain -> twinrl.render.camera"]


def test_imports_point_down_the_layers():
    edges = {name: deps for name, (deps, _) in GRAPH.items()}
    up = _upward(edges)
    assert not up, "imports that point up the layers:\n" + "\n".join(up)


def test_the_loop_is_a_list_of_stages():
    # loop.run only picks a family and walks its stages (each saves and loads its own values)
    tree = ast.parse(MODULES["twinrl.loop"].read_text())
    run = next(n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "run")
    assert run.end_lineno - run.lineno + 1 <= 60
    from twinrl import loop

    assert [s.name for s in loop.ROUND] == ["sysid", "hybrid", "learn", "compare", "residual",
                                            "deploy"]
    given = {"data"}
    for stage in loop.ROUND:  # every stage needs only what the round or earlier stages give
        assert set(stage.needs) <= given, (stage.name, stage.needs, given)
        given |= set(stage.gives)


MAX_TRAINER_LINES = 300


def _trainer_lengths(sources: dict[str, str]) -> dict[str, int]:
    """Line counts of the modules (name -> source) that define a trainer: a top-level function
    ``train`` or ``*_train`` (``ppo_train``; not ``runner.train_run``, which runs one)."""
    lengths = {}
    for name, source in sources.items():
        tree = ast.parse(source)
        if any(isinstance(n, ast.FunctionDef) and (n.name == "train" or n.name.endswith("_train"))
               for n in tree.body):
            lengths[name] = len(source.splitlines())
    return lengths


def test_the_trainer_finder_finds_a_long_trainer():
    long = "def train(env):\n" + "    pass\n" * MAX_TRAINER_LINES
    found = _trainer_lengths({"a": long, "b": "def ppo_train():\n    pass\n",
                              "c": "def train_run():\n    pass\n"})
    assert found == {"a": MAX_TRAINER_LINES + 1, "b": 2}


def test_no_trainer_is_over_300_lines():
    # the structure rule: no trainer module over ~300 lines (the shared kit, trainer.py,
    # windows.py, critic.py, common.py, holds what trainers have in common)
    learn = {name: path.read_text() for name, path in MODULES.items()
             if name.startswith("twinrl.learn.")}
    lengths = _trainer_lengths(learn)
    assert {"twinrl.learn.pods", "twinrl.learn.hds", "twinrl.learn.shac",
            "twinrl.learn.baselines"} <= set(lengths)
    too_long = {name: n for name, n in lengths.items() if n > MAX_TRAINER_LINES}
    assert not too_long, f"trainer modules over {MAX_TRAINER_LINES} lines: {too_long}"
