"""Task-inference methods: BATI and the paper's baselines, all on the shared IQL core."""

from __future__ import annotations

from bati.methods.base import MethodSpec, TaskInference
from bati.methods.bati import BATI, BATIAuto, BATIReward
from bati.methods.csro import CSRO
from bati.methods.dpt import DPT
from bati.methods.er_trl import ERTRL
from bati.methods.focal import FOCAL
from bati.methods.no_context import NoContext
from bati.methods.oracle import Oracle
from bati.methods.recon import Recon
from bati.methods.unicorn import UNICORN

METHODS = {"bati": BATI, "bati-r": BATIReward, "bati-auto": BATIAuto, "recon": Recon, "unicorn": UNICORN, "csro": CSRO,
           "focal": FOCAL, "er-trl": ERTRL, "dpt": DPT, "oracle": Oracle, "no-context": NoContext}


def method_names(names: tuple[str, ...] | list[str]) -> list[str]:
    """The methods `names` stands for, in order, without repeats; `all` stands for every method. Unknown
    names are a ValueError naming them and the choices."""
    unknown = [m for m in dict.fromkeys(names) if m != "all" and m not in METHODS]  # `all bogus` too
    chosen = list(METHODS) if "all" in names else list(dict.fromkeys(names))
    if unknown or not chosen:
        raise ValueError(f"unknown method(s) {', '.join(map(repr, unknown)) or '(none given)'}; "
                         f"choose from: {', '.join(METHODS)}, or all")
    return chosen


def training_of(name: str) -> str:
    """The method whose training run `name`'s is (`TaskInference.trains_as`; itself when it trains its own way)."""
    return METHODS[name].trains_as or name


def check_rules(method: str, rules, own_data: bool = False) -> tuple[str, ...]:
    """The test-time rules to evaluate in runs of `method`, once each: methods that train exactly as it
    (`training_of`). ValueError (one line) for one that trains otherwise, or for any on your own datasets
    (`own_data`: no p_train and p_test contexts)."""
    rules = tuple(dict.fromkeys(rules))
    for rule in rules:
        if rule not in METHODS:
            raise ValueError(f"unknown test-time rule {rule!r}; choose from: {', '.join(METHODS)}")
        if rule == method or training_of(rule) != training_of(method):
            raise ValueError(f"{rule!r} is not a test-time rule of a {method!r} run (it does not train exactly "
                             "as it; bati, bati-r and bati-auto train alike)")
    if rules and own_data:
        raise ValueError("test-time rules are evaluated on a family's p_train and p_test contexts, not on your own "
                         "datasets: train each method on its own")
    return rules


def make_method(name: str, spec: MethodSpec, config=None) -> TaskInference:
    """Method `name` for data described by `spec`, with its hyperparameters `config` (an instance of
    its `Config`; default: the Config's defaults, family-dependent ones from `spec.family`)."""
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}; choose one of: {', '.join(METHODS)}")
    return METHODS[name](spec, config)


__all__ = ["METHODS", "MethodSpec", "TaskInference", "make_method", "method_names", "training_of"]


def section_methods() -> dict[str, type]:
    """Each hyperparameter section of the methods in METHODS, in its order: `config_key` -> the first method
    declaring it (bati, bati-r and bati-auto share `bati`, and so its Config). TrainConfig has one field each."""
    first = {}
    for name, cls in METHODS.items():
        if cls.config_key is not None and first.setdefault(cls.config_key, cls).Config is not cls.Config:
            raise TypeError(f"{name} reads the section {cls.config_key!r} with a Config of its own "
                            f"({cls.Config.__name__}, not {first[cls.config_key].Config.__name__})")
    return first


def method_sections() -> dict[str, type]:
    """The hyperparameter sections: name -> the Config dataclass it holds."""
    return {key: method.Config for key, method in section_methods().items()}


def section_readers(section: str) -> list[str]:
    """The methods that read the hyperparameter section `section` (e.g. bati, bati-r and bati-auto read `bati`)."""
    return [name for name, cls in METHODS.items() if cls.config_key == section]


def method_config_key(method: str) -> str | None:
    """The section holding `method`'s hyperparameters (None: it has none, or is unknown)."""
    cls = METHODS.get(method)
    return None if cls is None else cls.config_key
