"""Task and method registries: contents, duplicates, unknown names, config building."""
import dataclasses

import pytest

from bench import plugins
from bench.api import MethodSpec, Uses
from bench.plugins import ConfigError, UnknownMethodError, build_config, get_method
from tasks import TASKS, UnknownTaskError, get_spec, register

PAPER_TASKS = {"ant", "hopper", "humanoid", "reacher", "walker2d", "swimmer",
               "inverted_pendulum", "acrobot"}


def test_registry_holds_the_paper_tasks_pointmass_and_cloth():
    assert PAPER_TASKS | {"pointmass", "cloth"} <= set(TASKS)
    for spec in TASKS.values():
        assert spec.episode_length == (80 if spec.name == "cloth" else 128)
        assert spec.backend in ("generalized", "positional", "spring", "analytic", "cloth")


def test_reregistering_a_task_raises():
    with pytest.raises(ValueError, match="already registered"):
        register(TASKS["hopper"])


def test_unknown_task_lists_valid_names():
    with pytest.raises(UnknownTaskError, match="unknown task 'hoper'.*hopper"):
        get_spec("hoper")


def test_specs_are_frozen():
    with pytest.raises(dataclasses.FrozenInstanceError):
        TASKS["hopper"].backend = "mjx"


def test_bc_is_registered_with_its_declaration():
    bc = get_method("bc")
    assert bc.uses == Uses(demo_states=True, demo_actions=True)
    assert bc.uses.describe() == "demo states, demo actions"


def test_unknown_method_lists_valid_names():
    with pytest.raises(UnknownMethodError, match="unknown method 'bcc'.*bc"):
        get_method("bcc")


def _fake_spec(name):
    @dataclasses.dataclass(frozen=True)
    class Cfg:
        lr: float = 1e-3
    return MethodSpec(name=name, train=lambda *a: None, config_cls=Cfg, uses=Uses())


def test_duplicate_method_raises():
    with pytest.raises(ValueError, match="registered twice"):
        plugins.register(_fake_spec("bc"), source="test")


class _EntryPoint:
    def __init__(self, name):
        self.name, self.value = name, "extpkg:METHOD"

    def load(self):
        return _fake_spec(self.name)


def _fresh_registry_with_entry_point(monkeypatch, name):
    monkeypatch.setattr(plugins, "_REGISTRY", {})
    monkeypatch.setattr(plugins, "_SOURCES", {})
    monkeypatch.setattr(plugins, "_loaded", False)
    real = plugins.metadata.entry_points
    # Only ildbench's group: other libraries read entry points too (torch's import does).
    monkeypatch.setattr(plugins.metadata, "entry_points",
                        lambda group: [_EntryPoint(name)] if group == plugins.ENTRY_POINT_GROUP
                        else real(group=group))


def test_entry_point_methods_are_discovered(monkeypatch):
    _fresh_registry_with_entry_point(monkeypatch, "extmethod")
    found = plugins.all_methods()
    assert "extmethod" in found and "bc" in found
    assert "entry point" in plugins._SOURCES["extmethod"]


def test_entry_point_duplicating_an_in_repo_name_raises(monkeypatch):
    _fresh_registry_with_entry_point(monkeypatch, "bc")
    with pytest.raises(ValueError, match="'bc' is registered twice"):
        plugins.all_methods()


def test_config_layers_and_coercion():
    bc = get_method("bc")
    cfg = build_config(bc, "pointmass", "cpu", {"updates": "300", "hidden": "64,32"})
    assert cfg.updates == 300 and cfg.hidden == (64, 32)
    assert build_config(bc, "pointmass").learning_rate == 1e-3  # the paper's default


@pytest.mark.parametrize("overrides,match", [
    ({"lerning_rate": "1"}, "no config field 'lerning_rate'"),
    ({"updates": "many"}, "expects int"),
    ({"updates": "0"}, "updates must be >= 1"),
    ({"learning_rate": "-1"}, "learning_rate must be > 0"),
])
def test_invalid_config_is_a_clear_error(overrides, match):
    with pytest.raises(ConfigError, match=match):
        build_config(get_method("bc"), "pointmass", None, overrides)


@dataclasses.dataclass(frozen=True)
class Cfg:
    """A toy method's config: a rewrite, a piece of it, a number."""
    rewrite: bool = False
    piece: bool = False
    lr: float = 1.0


def test_a_task_override_goes_with_the_field_it_requires():
    """`MethodSpec.requires`: a field a task override turned on goes back to its default when
    a later layer (preset or user) turns off the field it needs; one the user or a preset
    sets stays (and meets the config's own check); a needed field left on keeps it."""
    spec = MethodSpec(name="toy", train=lambda *a: None, config_cls=Cfg, uses=Uses(),
                      presets={"off": {"rewrite": False}},
                      task_overrides={"t": {"rewrite": True, "piece": True, "lr": 2.0}},
                      requires={"piece": "rewrite"})
    assert build_config(spec, "t") == Cfg(True, True, 2.0)
    assert build_config(spec, "t", None, {"rewrite": "false"}) == Cfg(False, False, 2.0)
    assert build_config(spec, "t", "off") == Cfg(False, False, 2.0)
    assert build_config(spec, "t", None, {"rewrite": "false", "piece": "true"}
                        ) == Cfg(False, True, 2.0)  # asked for: kept (no check in Cfg)
    assert build_config(spec, "t", None, {"lr": "3"}) == Cfg(True, True, 3.0)
    assert build_config(spec, "u", None, {"piece": "true"}) == Cfg(False, True, 1.0)


def test_platform_overrides_sit_between_the_tasks_and_the_preset(monkeypatch):
    """`MethodSpec.platform_overrides`: the platform's per-task fields win over the task's,
    lose to a preset's and the user's; one that turns a needed field off takes the task's
    dependent field along; another platform or task sees none of them; without `platform`
    build_config reads `current_platform()` (JAX's default backend: as on a GPU machine
    when it says 'gpu')."""
    spec = MethodSpec(name="toy", train=lambda *a: None, config_cls=Cfg, uses=Uses(),
                      presets={"fast": {"lr": 5.0}},
                      task_overrides={"t": {"rewrite": True, "piece": True, "lr": 2.0}},
                      platform_overrides={"gpu": {"t": {"rewrite": False, "lr": 3.0}}},
                      requires={"piece": "rewrite"})
    assert build_config(spec, "t", platform="cpu") == Cfg(True, True, 2.0)
    assert build_config(spec, "t", platform="gpu") == Cfg(False, False, 3.0)
    assert build_config(spec, "t", "fast", platform="gpu") == Cfg(False, False, 5.0)
    assert build_config(spec, "t", None, {"rewrite": "true"}, platform="gpu"
                        ) == Cfg(True, True, 3.0)  # the user's rewrite keeps the task's piece
    assert build_config(spec, "u", platform="gpu") == Cfg(False, False, 1.0)
    import jax
    assert plugins.current_platform() == jax.default_backend()
    for here, want in (("cpu", Cfg(True, True, 2.0)), ("gpu", Cfg(False, False, 3.0))):
        monkeypatch.setattr(plugins, "current_platform", lambda here=here: here)
        assert build_config(spec, "t") == want, here
    typo = dataclasses.replace(spec, name="toy_typo",
                               platform_overrides={"gpu": {"t": {"rewrit": False}}})
    with pytest.raises(ConfigError, match=r"platform_overrides\['gpu'\]\['t'\] names no "
                                          r"config field \['rewrit'\]"):
        plugins.register(typo)
    assert "toy_typo" not in plugins._REGISTRY


def test_unknown_preset():
    with pytest.raises(ConfigError, match="no preset 'gpu'"):
        build_config(get_method("bc"), "pointmass", "gpu")


def _fresh_registry_where_dac_misses(monkeypatch, module):
    """A fresh registry (plus one entry-point method) in which importing methods.dac fails
    because `module` is not installed."""
    real_import = plugins.importlib.import_module

    def import_module(name, *a, **k):
        if name == "methods.dac":
            raise ModuleNotFoundError(f"No module named {module!r}", name=module)
        return real_import(name, *a, **k)

    _fresh_registry_with_entry_point(monkeypatch, "extmethod")
    monkeypatch.setattr(plugins, "_UNAVAILABLE", {})
    monkeypatch.setattr(plugins.importlib, "import_module", import_module)


def test_method_with_a_missing_dependency_leaves_the_others_usable(monkeypatch):
    """A machine without gymnasium (the accelerator image) still runs the JAX methods, and
    asking for DAC names the missing package instead of failing every command."""
    _fresh_registry_where_dac_misses(monkeypatch, "gymnasium")
    names = plugins.all_methods()
    assert "dac" not in names and {"ild", "bc", "extmethod"} <= set(names)
    with pytest.raises(plugins.MethodUnavailableError, match="dac.*gymnasium.*pip install"):
        plugins.get_method("dac")
    with pytest.raises(plugins.UnknownMethodError, match="methods/dac not loadable.*gymnasium"):
        plugins.get_method("nosuch")
    assert plugins.get_method("ild").name == "ild"


def test_a_missing_module_of_our_own_is_not_hidden(monkeypatch):
    _fresh_registry_where_dac_misses(monkeypatch, "methods.common.gone")
    with pytest.raises(ModuleNotFoundError, match="methods.common.gone"):
        plugins.all_methods()
