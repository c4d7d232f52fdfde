"""On-disk layout of a collection: one Minari dataset per task, a manifest, an array cache.

```
<root>/<Family>/<scale>-seed<S>-eps<eps>/     one collection (renamed into place when complete)
    manifest.json                             written last: its presence marks a complete collection;
                                              `files`: each dataset file's size and sha256 (format >= 2)
    train-00-v0/ ... train-19-v0/             Eq. 9 offline datasets of the 20 training tasks
    p_test-00-v0/ ... p_test-19-v0/           Eq. 10 context data of the 20 test tasks
    p_train-00-v0/ ... p_train-19-v0/         p_train-style context data of the 20 test tasks
    arrays.npz                                flat-array cache written by the loader (optional)
<root>/<Family>/.<scale>-seed<S>-eps<eps>.lock  held while the collection is written (see bati.io.hold_lock)
```

Each dataset directory is a standard Minari dataset (HDF5 storage): point `MINARI_DATASETS_PATH`
at the collection directory and `minari.load_dataset("train-00-v0")` reads it.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import shutil
import warnings
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from bati.envs import TaskFamily, TaskSplit
from bati.experts.kinds import ExpertsKind, family_experts
from bati.io import pid_alive

MANIFEST = "manifest.json"
ARRAY_CACHE = "arrays.npz"
FORMAT_VERSION = 2
CHECKSUM_FORMAT = 2  # manifests from this format on record every dataset file's size and sha256
READABLE_FORMATS = (1, 2)
SPLITS = ("train", "p_test", "p_train")
DATASET_VERSION = 0  # Minari ids need a version suffix: "train-00-v0"
DEFAULT_ROOT = Path("data")
REQUIRED_KEYS = ("collection_id", "n_episodes", "n_context_episodes", "episode_length", "obs_dim",
                 "action_dim", "train_tasks", "test_tasks", "datasets")


class DatasetNotFoundError(FileNotFoundError):
    """A collection (or one of its datasets) is not on disk; the message says how to collect it."""


class DatasetError(ValueError):
    """A dataset on disk is unreadable, incomplete, or does not match its family's env."""


# --- names and paths -------------------------------------------------------------------------
def collection_name(scale: str, seed: int, noise: float) -> str:
    return f"{scale}-seed{seed}-eps{noise:g}"


def collection_dir(root: str | Path, family: TaskFamily, scale: str, seed: int, noise: float,
                   tasks: TaskSplit | None = None, experts: ExpertsKind | None = None) -> Path:
    """`<root>/<Family>/<scale>-seed<S>-eps<eps>[<split>][-v<version>]` (noise already validated / defaulted);
    a non-default task split adds its label, e.g. `-tasks10x30` or `-train0to3.14159-test3.14159to6.28319`,
    and an env version after the first its number (so the data of an earlier version stays where it was);
    data collected by per-task experts (App. C.2) ends in `-per-task-experts`."""
    experts = family_experts(family, experts, seed, tasks)
    label = ("" if tasks is None else tasks.label()) + ("-per-task-experts" if experts == "per-task" else "")
    version = family.record.version
    return Path(root) / family.name / (collection_name(scale, seed, noise) + label + (f"-v{version}" if version > 1 else ""))


def dataset_name(split: str, index: int) -> str:
    """Minari dataset id of task `index` of a split, e.g. "p_test-07-v0"."""
    return f"{split}-{index:02d}-v{DATASET_VERSION}"


def collect_command(family: TaskFamily, scale: str, seed: int, noise: float, root: str | Path,
                    tasks: TaskSplit | None = None, experts: ExpertsKind | None = None) -> str:
    """The exact `bati data collect ...` command that builds this collection."""
    command = f"bati data collect --family {family.name} --scale {scale} --seed {seed}"
    if noise != family.default_noise:
        command += f" --noise {noise:g}"
    tasks = tasks or TaskSplit()
    if (tasks.n_train, tasks.n_test) != (20, 20):
        command += f" --n-train {tasks.n_train} --n-test {tasks.n_test}"
    for side, task_range in (("train", tasks.train_range), ("test", tasks.test_range)):
        if task_range is not None:
            command += f" --{side}-range {task_range[0]:.17g} {task_range[1]:.17g}"
    if family_experts(family, experts, seed, tasks) != family_experts(family, None, seed, tasks):
        command += f" --experts {experts}"
    if Path(root) != DEFAULT_ROOT:
        command += f" --root {root}"
    return command


# --- manifest ----------------------------------------------------------------------------------
def read_manifest(path: Path, family: TaskFamily, scale: str, seed: int, noise: float, root,
                  tasks: TaskSplit | None = None, experts: ExpertsKind | None = None) -> dict:
    """The manifest of a complete collection, or DatasetNotFoundError / DatasetError."""
    tasks, experts = tasks or TaskSplit(), family_experts(family, experts, seed, tasks)
    redo_command = collect_command(family, scale, seed, noise, root, tasks, experts)
    manifest_path = path / MANIFEST
    if not manifest_path.is_file():
        raise DatasetNotFoundError(
            f"no {family.name} data at {path} (scale={scale}, seed={seed}, eps={noise:g}); "
            f"collect it with `{redo_command}`"
        )
    try:
        manifest = json.loads(manifest_path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise DatasetError(f"{manifest_path} is corrupted ({err}); delete {path} and re-run "
                           f"`{redo_command}`") from err
    redo = f"delete {path} and re-run `{redo_command}`"
    if not isinstance(manifest, dict):
        raise DatasetError(f"{manifest_path} holds a JSON {type(manifest).__name__}, not a manifest; {redo}")
    if manifest_edited(manifest):
        raise DatasetError(f"{manifest_path} was edited after the collection (its fields no longer match its "
                           f"{MANIFEST_DIGEST}); {redo}")
    if manifest.get("format") not in READABLE_FORMATS:
        raise DatasetError(f"{manifest_path}: format is {manifest.get('format')!r}, this bati reads "
                           f"{' or '.join(map(str, READABLE_FORMATS))}; {redo}")
    expected = {"family": family.name, "scale": scale, "seed": seed, "noise": noise, "experts": experts}
    for key, value in expected.items():
        if manifest.get(key, "conditioned" if key == "experts" else None) != value:
            raise DatasetError(f"{manifest_path}: {key} is {manifest.get(key)!r}, expected {value!r}; {redo}")
    missing = [key for key in REQUIRED_KEYS if key not in manifest]
    if missing:
        raise DatasetError(f"{manifest_path} lacks {', '.join(missing)}; {redo}")
    version = manifest.get("family_version", 1)  # collections made before versions existed: version 1
    if version != family.record.version:
        raise DatasetError(f"{path} holds {family.name} data of env version {version}; this bati's {family.name} is "
                           f"version {family.record.version} (docs/environments.md says what changed); {redo}")
    train, test = tasks.draw(family, seed)
    for name, expected_tasks in (("train_tasks", train), ("test_tasks", test)):
        stored = manifest[name]
        if len(stored) != len(expected_tasks) or not np.allclose(np.asarray(stored, float),
                                                                 np.asarray(expected_tasks, float)):
            drawn = f"{family.name}.split_tasks({seed})" if tasks.is_default else f"the split {tasks.record()}"
            raise DatasetError(f"{manifest_path}: its {name} are not {drawn} "
                               f"(collected with another task sampler?); {redo}")
    return manifest


# --- integrity: the size and sha256 of every dataset file -------------------------------------
def dataset_files(path: Path, datasets: dict[str, list[str]]) -> list[str]:
    """Every file of the collection's datasets, relative to the collection directory, sorted."""
    names = [name for split in SPLITS for name in datasets.get(split, [])]
    files = (f for name in names for f in (path / name).rglob("*") if f.is_file())
    return sorted(f.relative_to(path).as_posix() for f in files)


def sha256_file(file: Path) -> str:
    digest = hashlib.sha256()
    with open(file, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


MANIFEST_DIGEST = "manifest_sha256"


def manifest_digest(manifest: dict) -> str:
    """sha256 of a manifest's own fields (as JSON with sorted keys, without this digest): an edit by hand of
    any field (the tasks, the sizes) no longer matches the digest the collection recorded."""
    fields = {k: v for k, v in json.loads(json.dumps(manifest, default=str)).items() if k != MANIFEST_DIGEST}
    return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()


def manifest_edited(manifest: dict) -> bool:
    """Whether a manifest that records its digest no longer matches it (one from before digests: False)."""
    return MANIFEST_DIGEST in manifest and manifest[MANIFEST_DIGEST] != manifest_digest(manifest)


def file_checksums(path: Path, datasets: dict[str, list[str]]) -> dict[str, dict]:
    """{relative path: {"bytes", "sha256"}} of every dataset file: the manifest's record of what it wrote."""
    return {rel: {"bytes": (path / rel).stat().st_size, "sha256": sha256_file(path / rel)}
            for rel in dataset_files(path, datasets)}


def has_checksums(manifest: dict) -> bool:
    """Whether the manifest records its files (format >= CHECKSUM_FORMAT; older collections do not)."""
    return isinstance(manifest.get("files"), dict)


def file_problems(path: Path, manifest: dict, *, checksums: bool) -> list[str]:
    """What is wrong with the collection's files, one phrase each naming the file ([] when intact).

    Sizes and presence always: a stat per file, cheap enough for every load, and it catches a
    truncated or missing file. With `checksums` also each file's sha256 (reads every byte: `bati data
    verify`, and once when the loader builds its array cache), which catches an edit of the same size.
    Older manifests record no files: nothing to compare ([]).
    """
    if not has_checksums(manifest):
        return []
    problems, missing = [], set()
    for rel, recorded in sorted(manifest["files"].items()):
        file, dataset = path / rel, path / Path(rel).parts[0]
        if not dataset.is_dir():
            if dataset not in missing:
                problems.append(f"{dataset} is missing")
                missing.add(dataset)
            continue
        if not file.is_file():
            problems.append(f"{file} is missing")
            continue
        want = recorded.get("bytes") if isinstance(recorded, dict) else None
        size = file.stat().st_size
        if not isinstance(want, int):
            problems.append(f"{path / MANIFEST} records no size for {rel}")
        elif size < want:
            problems.append(f"{file} is truncated ({size:,} of {want:,} bytes)")
        elif size > want:
            problems.append(f"{file} has grown ({size:,} bytes, {want:,} recorded)")
        elif checksums and sha256_file(file) != recorded.get("sha256"):
            problems.append(f"{file} was edited (its sha256 differs from the manifest's)")
    return problems


def file_stamps(path: Path, manifest: dict) -> str:
    """The size and modification time of each of the collection's files, as one JSON string: what a cache
    built from them records, so that a file changed afterwards (even to the same size) is noticed."""
    stamps = {}
    for rel in sorted(manifest.get("files") or {}):
        try:
            stat = (path / rel).stat()
        except OSError:
            stamps[rel] = None
        else:
            stamps[rel] = [stat.st_size, stat.st_mtime_ns]
    return json.dumps(stamps, sort_keys=True)


def require_env_dims(path: Path, manifest: dict, family: TaskFamily, noise: float) -> tuple[int, int]:
    """The family's env's (obs_dim, action_dim); DatasetError when the collection recorded others (the env
    changed after it was collected without a version bump)."""
    probe = family.make_env(manifest["train_tasks"][0], noise)
    dims = probe.observation_space.shape[0], probe.action_space.shape[0]
    probe.close()
    if (manifest.get("obs_dim"), manifest.get("action_dim")) != dims:
        raise DatasetError(f"{path / MANIFEST}: obs_dim/action_dim {manifest.get('obs_dim')}/"
                           f"{manifest.get('action_dim')} do not match the {family.name} env's {dims[0]}/{dims[1]}; "
                           f"delete {path} and re-collect the data")
    return dims


def require_intact(path: Path, manifest: dict, redo: str, *, checksums: bool = False) -> None:
    """DatasetError (one line naming the first damaged file) unless the collection's files are as
    written; `redo` is the command that rebuilds it."""
    problems = file_problems(path, manifest, checksums=checksums)
    if problems:
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise DatasetError(f"{problems[0]}{more}: the collection {path} is damaged; `bati data verify --root "
                           f"{path.parents[1]}` lists every file; delete it and re-run `{redo}`")


def verify_collection(path: Path) -> tuple[str, list[str]]:
    """`bati data verify` of one collection directory: ("ok" | "damaged" | "unchecked", details)."""
    manifest_path = path / MANIFEST
    if not manifest_path.is_file():
        return "damaged", [f"{manifest_path} is missing (an interrupted or foreign collection)"]
    try:
        manifest = json.loads(manifest_path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as err:
        return "damaged", [f"{manifest_path} is unreadable ({err})"]
    if not isinstance(manifest, dict):
        return "damaged", [f"{manifest_path} holds a JSON {type(manifest).__name__}, not a manifest"]
    if not has_checksums(manifest):
        return "unchecked", [f"no checksums (collected before format {CHECKSUM_FORMAT})"]
    if manifest_edited(manifest):
        return "damaged", [f"{manifest_path} was edited after the collection (its fields no longer match its "
                           f"{MANIFEST_DIGEST})"]
    problems = file_problems(path, manifest, checksums=True)
    if problems:
        return "damaged", problems
    return "ok", [f"{len(manifest['files'])} files match their size and sha256"]


def inspect_collection(root: str | Path, family: TaskFamily, scale: str, seed: int, noise: float | None,
                       tasks: TaskSplit, experts: ExpertsKind | None = None) -> tuple[Path, dict]:
    """`bati data info`: the directory and manifest of a complete collection whose files all have their
    recorded sizes (cheap; `verify_collections` reads every byte); DatasetNotFoundError / DatasetError."""
    from bati.checks import check_integer

    check_integer("seed", seed, low=0)  # a negative seed: no collection has one, and none can be made
    noise = family.validate_noise(noise)
    tasks, experts = tasks.checked(family), family_experts(family, experts, seed, tasks)
    path = collection_dir(root, family, scale, seed, noise, tasks, experts)
    manifest = read_manifest(path, family, scale, seed, noise, root, tasks, experts)
    require_intact(path, manifest, collect_command(family, scale, seed, noise, root, tasks, experts))
    return path, manifest


def verify_collections(root: Path, family: TaskFamily | None = None, scale: str | None = None,
                       seed: int | None = None, noise: float | None = None) -> Iterator[tuple[Path, str, list[str]]]:
    """`bati data verify`: (path, status, details) of each collection under `root` matching the filters
    (`verify_collection`), one at a time as its files are hashed. Nothing to verify is a
    DatasetNotFoundError, raised before the first."""
    from bati.io import check_directory

    check_directory(root, "the data root", writable=False)
    if not Path(root).is_dir():
        raise DatasetNotFoundError(f"no data root {root}: nothing to verify")
    paths = find_collections(root, family.name if family else None, scale, seed, noise)
    if not paths:
        given = {"family": family.name if family else None, "scale": scale, "seed": seed, "noise": noise}
        which = ", ".join(f"{k}={v}" for k, v in given.items() if v is not None)
        raise DatasetNotFoundError(f"no collection under {root}" + (f" with {which}" if which else ""))
    return ((path, *verify_collection(path)) for path in paths)


_NAME = re.compile(r"^(?P<scale>[^-]+)-seed(?P<seed>\d+)-eps(?P<noise>[^-]+)")


def find_collections(root: Path, family: str | None = None, scale: str | None = None, seed: int | None = None,
                     noise: float | None = None) -> list[Path]:
    """The collection directories under `root` (`<root>/<Family>/<scale>-seed<S>-eps<eps>...`) that
    match the given settings (None matches any), found by name, so a damaged manifest is found too."""
    found = []
    families = [Path(root) / family] if family else sorted(p for p in Path(root).iterdir() if p.is_dir())
    for family_dir in families:
        if not family_dir.is_dir() or family_dir.name.startswith("."):
            continue
        for path in sorted(family_dir.iterdir()):
            match = _NAME.match(path.name)
            if path.name.startswith(".") or not path.is_dir() or not match:
                continue
            if ((scale is None or match["scale"] == scale) and (seed is None or int(match["seed"]) == seed)
                    and (noise is None or _float(match["noise"]) == noise)):
                found.append(path)
    return found


def _float(text: str) -> float | None:
    try:
        return float(text)
    except ValueError:
        return None


# --- Minari io ---------------------------------------------------------------------------------
@contextlib.contextmanager
def minari_root(path: Path) -> Iterator[None]:
    """Point Minari's datasets root (MINARI_DATASETS_PATH) at `path` for the duration."""
    previous = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(Path(path).resolve())  # Minari mangles relative roots
    try:
        yield
    finally:
        if previous is None:
            os.environ.pop("MINARI_DATASETS_PATH", None)
        else:
            os.environ["MINARI_DATASETS_PATH"] = previous


def write_dataset(
    directory: Path,
    name: str,
    family: TaskFamily,
    task: Any,
    noise: float,
    observations: np.ndarray,
    actions: np.ndarray,
    rewards: np.ndarray,
    episode_options: list[dict],
    episode_seeds: list[int],
    metadata: dict,
) -> None:
    """Write one task's episodes as the Minari dataset `directory/name`.

    observations: (E, T + 1, obs_dim) (the last one is the final next observation);
    actions (E, T, action_dim); rewards (E, T). `episode_options` are stored as each episode's
    Minari `options` (task parameters, collector); `metadata` under the dataset's "bati" key.
    """
    import gymnasium as gym
    import minari
    from minari.data_collector import EpisodeBuffer

    spec = replace(gym.spec(family.env_id), kwargs={"task": task, "noise": noise})
    n_episodes, length = rewards.shape
    truncations = np.zeros(length, dtype=bool)
    truncations[-1] = True  # the 200-step time limit; episodes never terminate
    buffers = [
        EpisodeBuffer(
            id=e,
            seed=int(episode_seeds[e]),
            options=episode_options[e],
            observations=observations[e],
            actions=actions[e],
            rewards=rewards[e],
            terminations=np.zeros(length, dtype=bool),
            truncations=truncations,
        )
        for e in range(n_episodes)
    ]
    with minari_root(directory), warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # Minari nags about author e-mail etc.
        dataset = minari.create_dataset_from_buffers(
            dataset_id=name,
            buffer=buffers,
            env=spec,
            eval_env=spec,
            algorithm_name="bati task-conditioned SAC experts (stochastic actions)",
            author="bati",
            code_permalink=f"bati@{metadata.get('commit', 'unknown')}",
            description=metadata.get("description"),
            data_format="hdf5",
        )
        dataset.storage.update_metadata({"bati": metadata})


def read_dataset(path: Path, obs_dim: int, action_dim: int, length: int) -> dict:
    """Read a whole Minari dataset into arrays, checking shapes against the family's env.

    Returns observations (E, T + 1, obs_dim) float32, actions (E, T, action_dim) float32,
    rewards (E, T) float32, options (list of per-episode option dicts) and metadata.
    """
    from minari import MinariDataset

    data_path = Path(path).resolve() / "data"
    if not data_path.is_dir():
        raise DatasetError(
            f"{path} is missing (the collection is incomplete); delete {path.parent} and re-collect"
        )
    file = data_path / "main_data.hdf5"
    try:
        dataset = MinariDataset(data_path)
        storage = dataset.storage
        meta = storage.metadata
        obs_shape = tuple(storage.observation_space.shape or ())
        act_shape = tuple(storage.action_space.shape or ())
        if obs_shape != (obs_dim,) or act_shape != (action_dim,):
            raise DatasetError(
                f"{data_path / 'metadata.json'}: observation/action spaces have shapes "
                f"{obs_shape}/{act_shape}, but the family's env has ({obs_dim},)/({action_dim},)"
            )
        indices = range(storage.total_episodes)
        episodes = list(storage.get_episodes(indices))
        options = [m.get("options", {}) for m in storage.get_episode_metadata(indices)]
    except DatasetError:
        raise
    except Exception as err:  # h5py / json / Minari errors on a damaged file
        raise DatasetError(f"{file}: cannot read the Minari dataset ({type(err).__name__}: {err})") from err
    if not episodes:
        raise DatasetError(f"{file}: the dataset holds no episodes")
    expected = {"observations": (length + 1, obs_dim), "actions": (length, action_dim), "rewards": (length,)}
    for episode in episodes:
        for key, shape in expected.items():
            value = np.asarray(episode[key])
            if value.shape != shape:
                raise DatasetError(
                    f"{file}: episode {episode['id']} has {key} of shape {value.shape}, expected {shape} "
                    f"(obs_dim={obs_dim}, action_dim={action_dim}, {length} steps, from the family's env)"
                )
    stack = {key: np.stack([np.asarray(ep[key]) for ep in episodes]).astype(np.float32) for key in expected}
    return {**stack, "options": options, "metadata": meta.get("bati", {})}


# --- atomic directories -------------------------------------------------------------------------
def lock_path(target: Path) -> Path:
    """The lock file held while `target` is collected: a hidden sibling, so the collection stays clean."""
    return target.parent / f".{target.name}.lock"


def partial_dir(target: Path) -> Path:
    """A fresh temporary sibling of `target` to collect into."""
    return target.parent / f".{target.name}.partial-{os.getpid()}-{os.urandom(4).hex()}"


def remove_stale_partials(target: Path) -> list[Path]:
    """Delete leftovers of crashed collections of `target` (partial dirs whose process is gone)."""
    removed = []
    if not target.parent.is_dir():
        return removed
    for candidate in target.parent.glob(f".{target.name}.partial-*"):
        try:
            pid = int(candidate.name.rsplit(".partial-", 1)[1].split("-")[0])
        except (IndexError, ValueError):
            pid = -1
        if pid != os.getpid() and _alive(pid):
            continue  # another process is collecting the same data right now
        shutil.rmtree(candidate, ignore_errors=True)
        removed.append(candidate)
    return removed


_alive = pid_alive  # a partial directory of a live process is another collection in progress


def save_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """np.savez straight to a temporary file, then rename (no in-memory copy of big arrays)."""
    tmp = path.parent / f".{path.name}.{os.getpid()}-{os.urandom(4).hex()}.tmp"
    try:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
