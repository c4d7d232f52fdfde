"""`TrainConfig`: everything a training run is, as one dataclass (the CLI is this dataclass, via tyro).

Its last fields are the methods' hyperparameter sections, one per `config_key` of the methods in
`bati.methods.METHODS`: the built-in ones declared, one for a method of your own added when this module is
imported. A run directory's config.json is `config.record()`:
the resolved config with only the run's own method's hyperparameters. A run's identity is that record,
where it lives aside (NOT_IDENTITY). Records of older versions are read by `bati.records`.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, fields, is_dataclass, replace
from functools import cache
from pathlib import Path
from typing import Annotated, Any, Literal, get_args, get_type_hints

import tyro

from bati.checks import check_finite_fields, check_hidden_dims, check_integer, check_number
from bati.cli_hints import DEFAULT_IN_DOC
from bati.data.batch import Collection
from bati.data.own import OWN_FAMILY, check_own_data, family_of  # noqa: F401 (family_of: imported from here by others)
from bati.envs import TaskFamily, TaskSplit
from bati.experts.kinds import ExpertsKind, family_experts
from bati.io import read_run_config
from bati.methods import METHODS, method_config_key, method_sections, section_methods, section_readers
from bati.methods.bati import BATI, BATIConfig
from bati.methods.csro import CSROConfig
from bati.methods.dpt import DPTConfig
from bati.methods.er_trl import ERTRL, ERTRLConfig
from bati.methods.focal import FOCALConfig
from bati.methods.unicorn import UNICORNConfig
from bati.records import (  # noqa: F401 (differing_settings, digest_view: imported from here by others)
    RECORD_ONLY,
    RECORD_VERSION,
    VERSION_KEY,
    differing_settings,
    digest_view,
    read_record,
)
from bati.rl.iql import TABLE3_HIDDEN_DIMS, IQLConfig
from bati.sinks import check_sinks

QUICK_RL_HIDDEN_DIMS = (128, 128)
"""IQL's hidden sizes at the quick and cpu scales (the paper scale uses Table 3's (256, 256))."""

ScaleName = Literal["quick", "cpu", "paper"]


@dataclass(frozen=True)
class Scale:
    """A named budget: the collection a run trains on and the defaults of its steps, batch and IQL nets."""

    data: Literal["quick", "paper"]
    """The collection (`bati data collect --scale`): quick (20 episodes per task) or paper (App. C's sizes)."""
    steps: int
    batch_size: int
    """Transitions per task in a batch (16 tasks per batch at every scale)."""
    hidden_dims: tuple[int, ...]
    """IQL's hidden sizes."""


SCALES: dict[str, Scale] = {
    "quick": Scale(data="quick", steps=3_000, batch_size=64, hidden_dims=QUICK_RL_HIDDEN_DIMS),
    # The paper's data and steps with the quick batch and nets: what a 2-core CPU affords
    # (docs/performance.md, "The cpu scale: wall time per run").
    "cpu": Scale(data="paper", steps=100_000, batch_size=64, hidden_dims=QUICK_RL_HIDDEN_DIMS),
    "paper": Scale(data="paper", steps=100_000, batch_size=256, hidden_dims=TABLE3_HIDDEN_DIMS),
}
"""The scales, each in one record: `quick` trains in a minute on a laptop, `paper` is App. C / Table 3."""


def get_scale(name: str) -> Scale:
    if name not in SCALES:
        raise ValueError(f"unknown scale {name!r}; choose one of: {', '.join(SCALES)}")
    return SCALES[name]


def with_registered_sections(cls: type) -> type:
    """`cls`, before it becomes a dataclass, with a field at its end for the section of each method registered
    in `METHODS` beyond the declared ones (a method of your own, docs/extending.md)."""
    for key, method in section_methods().items():
        if key not in cls.__annotations__:
            kind = method.Config
            if method.config_help is not None:
                kind = Annotated[kind, tyro.conf.arg(help=method.config_help)]
            cls.__annotations__[key] = kind
            setattr(cls, key, field(default_factory=method.Config))
    return cls


@dataclass
@with_registered_sections
class TrainConfig:
    family: Annotated[str | None, DEFAULT_IN_DOC] = None
    """The task family (default: PointGoal; with --datasets: `own`, your data)."""
    method: str = "bati"
    """bati, bati-r, bati-auto, recon, unicorn, csro, focal, er-trl, dpt, oracle or no-context."""
    seed: int = 0
    scale: ScaleName = "quick"
    """quick (20 episodes per task, 3k steps), cpu (the paper's data and steps, the quick batch and nets) or
    paper (App. C / Table 3); each names its collection and the defaults below (`SCALES`)."""
    steps: Annotated[int | None, DEFAULT_IN_DOC] = None
    """Gradient steps (default: the scale's: quick 3k, cpu and paper 100k)."""
    task_batch: Annotated[int | None, DEFAULT_IN_DOC] = None
    """Tasks in a batch (default: Table 3's 16, or all training tasks when there are fewer)."""
    batch_size: Annotated[int | None, DEFAULT_IN_DOC] = None
    """Transitions per task in a batch (default: the scale's: paper 256, quick and cpu 64)."""
    context_length: Annotated[int | None, DEFAULT_IN_DOC] = None
    """Transitions in a training context (encoder methods) and, by default, in an evaluation context
    (default: the family's, one episode = 200; KuhnPoker 20 = 10 hands)."""
    eval_context_length: Annotated[int | None, DEFAULT_IN_DOC] = None
    """Transitions in an evaluation context (default: context_length; Table 1 evaluates other lengths)."""
    eval_every: Annotated[int | None, DEFAULT_IN_DOC] = None
    """Steps between evaluations (default: a tenth of the steps)."""
    checkpoint_every: Annotated[int | None, DEFAULT_IN_DOC] = None
    """Steps between checkpoints (default: eval_every)."""
    eval_workers: int = 1
    """Processes that step the evaluation's MuJoCo envs (1: this one). The same numbers whatever the count;
    on a GPU machine evaluation is CPU-bound, so give it the spare cores. Not part of the run's identity."""
    eval_beside_training: bool = False
    """Evaluate in a thread while the next chunks train (on a GPU machine the device trains during the CPU-bound
    evaluation instead of idling); a checkpoint at an evaluation's step is saved once that evaluation's records
    are written. The same numbers either way. Not part of the run's identity."""
    log_every: int = 100
    noise: Annotated[float | None, DEFAULT_IN_DOC] = None
    """The family's eps for data and evaluation (default: the family's)."""
    data_seed: int = 0
    """Seed of the collection to train on (its `bati data collect --seed`)."""
    data_root: Path = Path("data")
    experts: Annotated[ExpertsKind | None, DEFAULT_IN_DOC] = None
    """Which experts collected the data: one SAC per training task (App. C.2's) or the family's one
    task-conditioned SAC (ours). Each is its own collection (default: per-task where the family has per-task
    experts, else its one expert: KuhnPoker's exact best responses, a family of your own)."""
    zoo_dir: Annotated[Path | None, DEFAULT_IN_DOC] = None
    """Where the family's expert is (default: the package zoo): it collects missing data, gives the expert
    reference return and DPT's labels (`bati experts train` exports into its run directory's zoo/)."""
    out_dir: Annotated[Path | None, DEFAULT_IN_DOC] = None
    """Run directory (default: runs/<family>/<scale>/<method>-seed<seed>)."""
    learning_rate: float = 3e-4
    """Adam step size of the task-inference method (IQL's is iql.learning_rate)."""
    iql: Annotated[IQLConfig, DEFAULT_IN_DOC] = field(default_factory=IQLConfig)
    """The offline RL core (default hidden sizes: quick and cpu (128, 128), paper Table 3's (256, 256))."""

    episodes_per_task: Annotated[int | None, DEFAULT_IN_DOC] = None
    """Episodes per training task in the data (default: the scale's; a collection of other sizes needs
    its own --data-root)."""
    context_episodes: Annotated[int | None, DEFAULT_IN_DOC] = None
    """Episodes per test task in the context data (default: the scale's)."""
    n_train_tasks: int = 20
    """Training tasks (App. D.3 splits AntDir's 40 tasks 10/30 and 30/10)."""
    n_test_tasks: int = 20
    train_task_range: tuple[float, float] | None = None
    """Draw the training tasks' parameter uniformly from [LOW, HIGH) (Sec. 5.7: AntDir 0 3.14159)."""
    test_task_range: tuple[float, float] | None = None
    """Draw the test tasks' parameter uniformly from [LOW, HIGH) (Sec. 5.7: AntDir 3.14159 6.28319)."""

    datasets: tuple[str, ...] = ()
    """Train on your own Minari datasets (ids or directories) instead of a family's collection: one per task,
    or grouped by --task-key (docs/own-data.md). No env: offline diagnostics instead of returns."""
    task_key: Annotated[str | None, DEFAULT_IN_DOC] = None
    """With --datasets: the key of each episode's Minari options that names its task (default: one task per
    dataset)."""
    held_out: float = 0.2
    """With --datasets: share of each task's segments held out for the diagnostics."""
    eval_env: str | None = None
    """With --datasets and --task-key: your env's gymnasium id ('package.module:Env-v0' imports the module
    first); returns are then measured in it, each task set by reset(options={TASK_KEY: value})."""
    log_to: tuple[str, ...] = ()
    """Also log to: tensorboard (`pip install 'bati[tensorboard]'`), wandb (`pip install 'bati[wandb]'`);
    the JSONL files are always written. Not part of the run's identity."""
    # Then each method's hyperparameters, a section per `config_key` (config.json records the run's own method's),
    # and the section of each method registered beyond these (`with_registered_sections`).

    bati: Annotated[BATIConfig, tyro.conf.arg(help=BATI.config_help)] = field(default_factory=BATIConfig)
    unicorn: UNICORNConfig = field(default_factory=UNICORNConfig)
    csro: CSROConfig = field(default_factory=CSROConfig)
    focal: FOCALConfig = field(default_factory=FOCALConfig)
    ertrl: Annotated[ERTRLConfig, tyro.conf.arg(help=ERTRL.config_help)] = field(default_factory=ERTRLConfig)
    dpt: DPTConfig = field(default_factory=DPTConfig)

    # --- reading and writing ------------------------------------------------------------------
    @classmethod
    def from_record(cls, record: dict) -> TrainConfig:
        """The config a run directory's config.json records, of any version (`read_record`; lists back to
        tuples; `runtime` and keys this version does not know are ignored). A section that is not an object of
        settings is one ValueError."""
        for name in nested_sections():
            if name in record and not isinstance(record[name], dict):
                raise ValueError(f"config setting {name!r} must be an object of settings, got "
                                 f"{type(record[name]).__name__} {record[name]!r}")
        record = read_record(record)
        kinds = {f.name: f for f in fields(cls)}
        values = {k: _tuples(v) for k, v in record.items() if k in kinds}
        for name, section in method_sections().items():
            if isinstance(values.get(name), dict):
                values[name] = _dataclass_from(section, values[name])
        if isinstance(values.get("iql"), dict):
            values["iql"] = _dataclass_from(IQLConfig, values["iql"])
        for name in ("data_root", "out_dir"):
            if values.get(name) is not None:
                values[name] = Path(values[name])
        return cls(**values)

    @classmethod
    def from_file(cls, path: Path) -> TrainConfig:
        """The config recorded in a run directory (or its config.json): `bati train --config`."""
        path = Path(path)
        record = read_run_config(path.parent if path.name == "config.json" else path)
        unknown = sorted(set(record) - {f.name for f in fields(cls)} - RECORD_ONLY)
        sections = {"iql": IQLConfig, **method_sections()}
        unknown += sorted(f"{name}.{key}" for name, section in sections.items() if isinstance(record.get(name), dict)
                          for key in set(record[name]) - {f.name for f in fields(section)})
        if unknown:  # a typo in a hand-edited config would otherwise train with the default
            raise ValueError(f"{path} has setting(s) this version does not know: {', '.join(map(repr, unknown))}")
        missing = [name for name in RECORDED if name not in record]
        if missing:  # taking the default would rerun another run than the one recorded
            file = path if path.name == "config.json" else path / "config.json"
            raise ValueError(f"{file} lacks {', '.join(missing)}: a run's config.json records every setting it ran "
                             "with; restore the file or start the run anew without --config")
        return cls.from_record(record)

    def record(self, family: TaskFamily | None = None) -> dict:
        """The config as JSON data (config.json): only the run's own method's hyperparameters. `family`: the
        config's family object, when the caller has it (its version is recorded)."""
        own = method_config_key(self.method)
        others = set(method_sections()) - {own}
        values = {f.name: getattr(self, f.name) for f in fields(self) if f.name not in others}
        values = {name: asdict(value) if is_dataclass(value) else value for name, value in values.items()}
        record = json.loads(json.dumps(values, default=str))
        if self.family not in (None, OWN_FAMILY):  # the env's version is part of what the run trained on
            record["family_version"] = (family or family_of(self.family)).record.version
        record[VERSION_KEY] = RECORD_VERSION
        return record

    def task_split(self) -> TaskSplit:
        """The training / test task split of the run's data."""
        return TaskSplit(self.n_train_tasks, self.n_test_tasks,
                         None if self.train_task_range is None else tuple(self.train_task_range),
                         None if self.test_task_range is None else tuple(self.test_task_range))

    @property
    def data_scale(self) -> str:
        """The scale of the collection the run trains on (the cpu scale trains on the paper's data)."""
        return get_scale(self.scale).data

    def method_config(self) -> Any:
        """The run's method's hyperparameters (None for a method without any)."""
        key = method_config_key(self.method)
        return None if key is None else getattr(self, key)

    # --- defaults and checks ------------------------------------------------------------------
    def resolved(self) -> ResolvedConfig:
        """Every default filled in (an explicit default and None give the same config) and every value
        checked, before any work: ValueError / TaskError with one line naming the setting."""
        return self.resolve().config

    def resolve(self, family: TaskFamily | None = None) -> ResolvedRun:
        """The run resolved into typed values (`ResolvedRun`: the config with every default filled, the family
        object, its collection), every value checked before any work. `family`: the config's family when the
        caller has looked it up already (one lookup by name per entry point)."""
        own = bool(self.datasets)
        self._check_data_source(own)
        name = OWN_FAMILY if own else (self.family or "PointGoal")
        if family is None:
            family = family_of(name, self.context_length)  # TaskError for an unknown family
        elif family.name != name:
            raise ValueError(f"resolving a {name} config with the family {family.name}")
        self._check_values(family)
        scale = get_scale(self.scale)
        pick = lambda value, default: default if value is None else value  # noqa: E731
        steps = pick(self.steps, scale.steps)
        tenth = max(self.log_every, (steps // 10) // self.log_every * self.log_every)
        eval_every = pick(self.eval_every, tenth)
        out = pick(self.out_dir, default_run_dir(name, self.scale, self.method, self.seed))
        split = None if own else self.task_split().checked(family)  # TaskError for a bad count or range
        if own:
            if METHODS[self.method].needs_expert_actions:
                raise ValueError(f"{self.method} imitates an expert of the tasks, which your own data does not have")
            if not 0.0 < self.held_out < 1.0:
                raise ValueError(f"held_out must be in (0, 1), got {self.held_out!r}")
            check_own_data(self.datasets, self.eval_env, self.task_key)  # before any work
        context_length = pick(self.context_length, family.default_context_length)
        rl_dims = pick(self.iql.hidden_dims, scale.hidden_dims)
        resolved = ResolvedConfig(**{
            **{f.name: getattr(self, f.name) for f in fields(TrainConfig)},
            "family": name,
            "datasets": tuple(self.datasets),
            "log_to": tuple(self.log_to),
            "noise": family.validate_noise(self.noise),
            "train_task_range": None if own else split.train_range,
            "test_task_range": None if own else split.test_range,
            "steps": steps,
            "batch_size": pick(self.batch_size, scale.batch_size),
            "task_batch": pick(self.task_batch, 16 if own else min(16, split.n_train)),
            "eval_every": eval_every,
            "context_length": context_length,
            "eval_context_length": pick(self.eval_context_length, context_length),
            "checkpoint_every": pick(self.checkpoint_every, eval_every),
            "out_dir": Path(out),
            "data_root": Path(self.data_root),
            "zoo_dir": None if self.zoo_dir is None else Path(self.zoo_dir),
            "experts": family_experts(family, self.experts, self.data_seed, split),
            "iql": replace(self.iql, hidden_dims=tuple(rl_dims), discrete=family.discrete_actions),
            **{name: _for_family(getattr(self, name), family.record) for name in method_sections()},
        })
        collection = None if own else Collection(
            family, resolved.data_scale, resolved.data_seed, resolved.noise, resolved.data_root, resolved.task_split(),
            resolved.experts, resolved.episodes_per_task, resolved.context_episodes)
        _check_resolved(resolved, collection)
        if collection is not None:
            collection.check_fits()  # a size that would exhaust the machine: one line, before any record
        return ResolvedRun(resolved, family, collection)

    def _check_data_source(self, own: bool) -> None:
        """Your own data (--datasets) or a family's collection, with the settings that belong to it (one line)."""
        if own and self.family not in (None, OWN_FAMILY):
            raise ValueError(f"--datasets trains on your own data (family {OWN_FAMILY!r}), not on {self.family}: "
                             "leave out --family")
        if not own and self.family == OWN_FAMILY:
            raise ValueError(f"family {OWN_FAMILY!r} is your own data: give it with --datasets")
        if not own and (self.task_key is not None or self.held_out != TrainConfig.held_out):
            name = "--task-key" if self.task_key is not None else "--held-out"
            raise ValueError(f"{name} applies to your own data: give it with --datasets")
        if self.eval_env is not None and not own:
            raise ValueError(f"--eval-env is your own data's env: the families' envs are built in (the "
                             f"{self.family or 'PointGoal'} runs are evaluated in theirs)")

    def _check_values(self, family: TaskFamily) -> None:
        """Every number, sink and method section of the config checked (one line each), before any default."""
        if self.method not in METHODS:
            raise ValueError(f"unknown method {self.method!r}; choose one of: {', '.join(METHODS)}")
        for setting in ("steps", "task_batch", "batch_size", "context_length", "eval_context_length", "eval_every",
                        "checkpoint_every", "log_every", "episodes_per_task", "context_episodes", "eval_workers"):
            if getattr(self, setting) is not None:  # None: the default; 0 is refused, never the default
                check_integer(setting, getattr(self, setting))
        for setting in ("seed", "data_seed"):
            check_integer(setting, getattr(self, setting), low=0)
        for setting, value in (("learning_rate", self.learning_rate), ("iql.learning_rate", self.iql.learning_rate),
                               ("iql.temperature", self.iql.temperature),
                               ("iql.max_exp_advantage", self.iql.max_exp_advantage)):
            check_number(setting, value)
        check_number("iql.expectile", self.iql.expectile, below=1.0)  # 1 (or 0): V ignores one side of Q
        for setting in ("discount", "tau"):
            check_number(f"iql.{setting}", getattr(self.iql, setting), at_most=1.0)
        check_sinks(self.log_to)  # an unknown sink, or its package missing: before any work
        check_foreign_sections(self, family.record)
        section = self.method_config()
        if is_dataclass(section):
            check_finite_fields(method_config_key(self.method), section)
        if hasattr(section, "check"):
            section.check(method_config_key(self.method))
        layers = {"iql.hidden_dims": self.iql.hidden_dims}
        if is_dataclass(section):
            layers |= {f"{method_config_key(self.method)}.{f.name}": getattr(section, f.name) for f in fields(section)
                       if f.name.endswith("hidden_dims")}
        for setting, dims in layers.items():
            if dims is not None:
                check_hidden_dims(setting, dims)

@dataclass(kw_only=True)
class ResolvedConfig(TrainConfig):
    """A config with every default filled in (`TrainConfig.resolve`): the values that run, typed as such; what
    config.json records. `episodes_per_task` and `context_episodes` stay None where the scale's sizes are meant
    (a record names a size only where one was given, so that its digest and run directory stay the same): the
    run's collection holds them (`Collection.sizes`). `zoo_dir` None is the package's experts; the task ranges are
    None on your own data only."""

    family: str = field()
    steps: int = field()
    task_batch: int = field()
    batch_size: int = field()
    context_length: int = field()
    eval_context_length: int = field()
    eval_every: int = field()
    checkpoint_every: int = field()
    noise: float = field()
    experts: ExpertsKind = field()
    out_dir: Path = field()


def _check_resolved(resolved: ResolvedConfig, collection: Collection | None) -> None:
    """What only the filled-in values can tell (one line): contexts longer than the data that holds them, a batch of
    more tasks than train, evaluations off the logging grid."""
    context_length = resolved.context_length
    if collection is None and resolved.eval_context_length > context_length:
        raise ValueError(f"eval_context_length ({resolved.eval_context_length}) must be at most context_length "
                         f"({context_length}): your episodes are cut into segments of context_length")
    if collection is not None:  # a context is cut from one test task's context data
        for setting in ("context_length", "eval_context_length"):
            collection.check_context_length(setting, getattr(resolved, setting))
    if resolved.method == "dpt" and resolved.dpt.max_length < max(context_length, resolved.eval_context_length):
        raise ValueError(f"dpt.max_length ({resolved.dpt.max_length}) must be >= the context length "
                         f"({max(context_length, resolved.eval_context_length)}): the transformer's positions "
                         "cover max_length transitions")
    if collection is not None and resolved.task_batch > collection.tasks.n_train:
        raise ValueError(f"task_batch ({resolved.task_batch}) must be at most n_train_tasks "
                         f"({collection.tasks.n_train}): a batch draws distinct training tasks")
    if resolved.eval_every % resolved.log_every or resolved.checkpoint_every % resolved.log_every:
        raise ValueError(f"eval_every ({resolved.eval_every}) and checkpoint_every ({resolved.checkpoint_every}) "
                         f"must be multiples of log_every ({resolved.log_every})")


@dataclass(frozen=True)
class ResolvedRun:
    """A run resolved once at its entry point (`TrainConfig.resolve`) and passed down as typed values."""

    config: ResolvedConfig
    """Every default filled in: what config.json records (names, not objects)."""
    family: TaskFamily
    """The family object (an OwnFamily on your own datasets)."""
    collection: Collection | None
    """The collection it trains on (None: your own datasets, `config.datasets`)."""

    def record(self) -> dict:
        """config.json's record of the run."""
        return self.config.record(self.family)

    def for_seed(self, seed: int, out_dir: Path | None = None) -> ResolvedRun:
        """The same run with another seed, in `out_dir` (default: the seed's default directory); the seed is
        not checked here (`bati.run_dir.check_seeds`)."""
        config = replace(self.config, seed=seed, out_dir=out_dir or default_run_dir(self.config.family,
                                                                                     self.config.scale,
                                                                                     self.config.method, seed))
        return replace(self, config=config)


def default_run_dir(family: str, scale: str, method: str, seed: int) -> Path:
    """Where a run goes when no --out-dir is given."""
    return Path("runs") / family / scale / f"{method}-seed{seed}"


def rerun_config(recorded: str | Path, given: TrainConfig) -> TrainConfig:
    """`bati train --config`: the config a run directory recorded (its directory or config.json), exactly,
    with `given`'s out_dir and, when not the default, data_root. Any other setting of `given` that differs
    from the defaults is a ValueError naming it (a rerun that silently changed it would not be one)."""
    default = TrainConfig()
    changed = [f.name for f in fields(TrainConfig) if f.name not in NOT_IDENTITY
               and getattr(given, f.name) != getattr(default, f.name)]
    if changed:
        raise ValueError(f"--config reruns a recorded config exactly: leave out --{changed[0].replace('_', '-')} "
                         "(only --out-dir, --data-root and --seeds may be given with it)")
    config = TrainConfig.from_file(recorded)
    return replace(config, out_dir=given.out_dir,
                   data_root=given.data_root if given.data_root != default.data_root else config.data_root)


def nested_sections() -> dict[str, type]:
    """TrainConfig's fields that are dataclasses themselves: IQL's and each method's."""
    return {"iql": IQLConfig, **method_sections()}


NOT_SETTABLE = ("iql.discrete",)
"""Derived from the family (KuhnPoker's actions are discrete), never set by hand."""


@cache
def settable_names() -> frozenset[str]:
    """Names `apply_settings` accepts: TrainConfig's plain fields and `section.field` of nested ones."""
    sections = nested_sections()
    names = {f.name for f in fields(TrainConfig) if f.name not in sections}
    names |= {f"{name}.{f.name}" for name, cls in sections.items() for f in fields(cls)}
    return frozenset(names - set(NOT_SETTABLE))


def apply_settings(config: TrainConfig, settings: dict[str, Any]) -> TrainConfig:
    """`config` with `settings` ({field or "section.field": value}) applied; ValueError for an unknown name."""
    names = settable_names()
    plain, nested = {}, {}
    for key, value in settings.items():
        if key not in names:
            raise ValueError(f"unknown setting {key!r}")
        section, _, name = key.partition(".")
        if name:
            nested.setdefault(section, {})[name] = value
        else:
            plain[key] = value
    sections = {section: replace(holder, **_typed(holder, values))
                for section, values in nested.items() for holder in [getattr(config, section)]}
    return replace(config, **_typed(config, plain), **sections)


def _typed(holder: Any, values: dict[str, Any]) -> dict[str, Any]:
    """`values` for the fields of the dataclass `holder`, an int given for a float field as that float: `x=1` and
    `x=1.0` are one setting (one config, one cell), not two."""
    hints = _field_types(type(holder))

    def typed(name: str, value: Any) -> Any:
        hint = hints.get(name)
        is_float = hint is float or float in get_args(hint)
        return float(value) if is_float and isinstance(value, int) and not isinstance(value, bool) else value
    return {name: typed(name, value) for name, value in values.items()}


@cache
def _field_types(cls: type) -> dict[str, Any]:
    """The dataclass `cls`'s field types, resolved once (a plan applies settings to hundreds of cells)."""
    return get_type_hints(cls)


def check_foreign_sections(config: TrainConfig, record) -> None:
    """ValueError (one line) when `config` sets another method's hyperparameters, which its method never
    reads (e.g. --focal.distance on a csro run: CSRO reads --csro.distance)."""
    own = method_config_key(config.method)
    for name, cls in method_sections().items():
        if name == own:
            continue
        given, default = _for_family(getattr(config, name), record), _for_family(cls(), record)
        changed = [f.name for f in fields(cls) if getattr(given, f.name) != getattr(default, f.name)]
        if changed:
            reads = f"which reads {own}.*" if own else "which has no hyperparameters of its own"
            raise ValueError(f"{name}.{changed[0]} is read by {', '.join(section_readers(name))} only, not by "
                             f"{config.method} ({reads})")


def _for_family(section, record):
    return section.for_family(record) if hasattr(section, "for_family") else section


def _tuples(value):
    if isinstance(value, list):
        return tuple(_tuples(v) for v in value)
    return value


def _dataclass_from(cls, values: dict):
    """An instance of dataclass `cls` from a record's dict (unknown keys ignored, lists as tuples)."""
    names = {f.name for f in fields(cls)}
    return cls(**{k: _tuples(v) for k, v in values.items() if k in names})


RECORDED = ("family", "method", "seed", "scale", "steps")
"""Settings every run's config.json holds since the first version: `--config` refuses a file without one."""

# Not what a run is: where it lives, how it is evaluated and logged (these may differ when a run directory is moved
# or resumed), and the version of its record's format.
NOT_IDENTITY = ("out_dir", "data_root", "log_to", "zoo_dir", "eval_workers", "eval_beside_training", VERSION_KEY)
