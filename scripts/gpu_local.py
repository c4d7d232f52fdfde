"""Your checkout's side of GPU work (the GPU machine's side is scripts/gpu_paper_scale.sh; docs/gpu.md).

    python scripts/gpu_local.py away       # optional, before copying the checkout to the GPU machine
    MODE=start ... bash scripts/gpu_paper_scale.sh   # there; then MODE=watch, and copy its $OUT folder back
    python scripts/gpu_local.py back       # after the GPU work (also when it failed)
    python scripts/gpu_local.py unpack <the copied-back folder> --logs .gpu/logs/<session>

`away` keeps the copy small: it pauses the cpu queue (SIGSTOP: it writes under results/), moves results/ out of the
checkout (to --stash) and leaves in .gpu/committed/ a slim copy of the committed cells of results/paper/experiments
(config.json, eval.json, eval.jsonl: what makes a cell finished there; the training logs, most of the bytes, stay
here). `back` undoes both. `unpack` takes the files a GPU command packed: its results.tar.gz (every result file but
checkpoints) and resume-*.tar (the checkpoint of each unfinished run); finished cells not yet committed go into
results/paper/experiments, the unfinished runs (with their checkpoints) into .gpu/resume/, which the next machine's
first command copies and resumes from instead of step 0, their logs (no checkpoints) and the GPU work's logs into
--logs, a new folder outside results/ (one per machine; .gpu/ is not committed: results/ holds finished cells only,
each recording its device, commit and wall time).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
COMMITTED = Path("results/paper/experiments")
SLIM_FILES = ("config.json", "eval.json", "eval.jsonl")
CHECKPOINT = "checkpoint.msgpack"
QUEUE_PATTERN = r"cpu_main_queue\.sh|bati\.cli"
COPY_LIMIT_VARIABLE = "BATI_COPY_LIMIT_MIB"
"""Set it to the size your copy to the GPU machine may have (MiB), if it is limited: `away` warns above it."""


class GpuLocalError(Exception):
    """One line for the user; nothing was moved."""


def run_dirs(tree: Path) -> list[Path]:
    """The run directories under `tree` (<family>/<setting>/<method>-seed<seed>: those holding a config.json)."""
    return sorted(p.parent for p in tree.glob("*/*/*/config.json"))


def copy_run(src: Path, dest: Path, files=None, checkpoint: bool = False) -> None:
    """Copy the run directory `src` to `dest` (replacing it): `files` only if given, the checkpoint only if asked."""
    if dest.exists():
        shutil.rmtree(dest)
    dest.mkdir(parents=True)
    for path in src.iterdir():
        if path.is_file() and (files is None or path.name in files) and (checkpoint or path.name != CHECKPOINT) \
                and not path.name.endswith((".lock", ".tmp")):
            shutil.copy2(path, dest / path.name)


def ancestors() -> set[int]:
    """This process and the ones above it (a shell whose command line names the pattern must not be stopped)."""
    pids, pid = set(), os.getpid()
    while pid > 1 and pid not in pids:
        pids.add(pid)
        try:
            pid = int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            break
    return pids


def paused_pids(root: Path) -> Path:
    return root / ".gpu" / "paused.json"


def away(root: Path, stash: Path, pause: bool) -> None:
    results = root / "results"
    if not results.is_dir():
        raise GpuLocalError(f"{results} is not there (already away? then `back` first)")
    if stash.exists():
        raise GpuLocalError(f"{stash} exists: a stash from an earlier `away`; move it back (`back`) or remove it")
    if stash.resolve().is_relative_to(root.resolve()):
        raise GpuLocalError(f"--stash {stash} is inside the checkout: it would be copied with it")
    slim = root / ".gpu" / "committed"
    if slim.exists():
        shutil.rmtree(slim)
    for run in run_dirs(root / COMMITTED):
        if (run / "eval.json").exists():
            copy_run(run, slim / run.relative_to(root / COMMITTED), files=SLIM_FILES)
    pids = []
    if pause:
        found = subprocess.run(["pgrep", "-f", QUEUE_PATTERN], capture_output=True, text=True).stdout.split()
        pids = [int(p) for p in found if int(p) not in ancestors()]
        for pid in pids:
            os.kill(pid, signal.SIGSTOP)
    paused_pids(root).parent.mkdir(exist_ok=True)
    paused_pids(root).write_text(json.dumps({"pids": pids, "stash": str(stash.resolve())}))
    try:
        shutil.move(str(results), str(stash))
    except OSError as err:  # nothing moved: let the queue go on
        for pid in pids:
            os.kill(pid, signal.SIGCONT)
        paused_pids(root).unlink()
        raise GpuLocalError(f"could not move {results} to {stash}: {err}") from err
    size = copy_size(root)
    print(f"results/ moved to {stash}; {len(run_dirs(slim))} committed cell(s) in .gpu/committed; "
          f"{len(pids)} queue process(es) paused; a copy of the checkout holds ~{size / 2**20:.1f} MiB with .whl and .gpu")
    limit = float(os.environ.get(COPY_LIMIT_VARIABLE) or "inf") * 2**20
    if size > limit:
        print(f"warning: over {limit / 2**20:.0f} MiB ({COPY_LIMIT_VARIABLE}): too much for your copy", file=sys.stderr)


def back(root: Path) -> None:
    record = paused_pids(root)
    if not record.exists():
        raise GpuLocalError(f"no {record}: nothing is away")
    state = json.loads(record.read_text())
    stash, results = Path(state["stash"]), root / "results"
    if stash.exists():
        if results.exists():
            raise GpuLocalError(f"both {results} and the stash {stash} exist: merge them by hand")
        shutil.move(str(stash), str(results))
    for pid in state["pids"]:
        try:
            os.kill(pid, signal.SIGCONT)
        except ProcessLookupError:
            pass
    record.unlink()
    shutil.rmtree(root / ".gpu" / "committed", ignore_errors=True)  # stale once results/ is back: the calls use it first
    print(f"results/ back from {stash}; {len(state['pids'])} queue process(es) resumed")


def copy_size(root: Path) -> int:
    """Bytes of what a copy of the checkout would hold: tracked and untracked-not-ignored files, plus .whl and .gpu."""
    listed = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=root, capture_output=True,
                            text=True).stdout.split("\0")
    total = sum((root / p).stat().st_size for p in listed if p and (root / p).is_file())
    for carried in (".whl", ".gpu"):
        total += sum(p.stat().st_size for p in (root / carried).rglob("*") if p.is_file())
    return total


def unpack(root: Path, folder: Path, logs: Path) -> None:
    pack = folder / "results.tar.gz"
    if not pack.is_file():
        raise GpuLocalError(f"no {pack}: no pack was copied back")
    committed = root / COMMITTED
    if not committed.is_dir():
        raise GpuLocalError(f"{committed} is not there: `back` first")
    if logs.is_dir() and any(logs.iterdir()):  # an earlier session's logs, committed perhaps: never overwrite them
        raise GpuLocalError(f"{logs} already holds files (an earlier session's logs?): name a new --logs folder")
    with tempfile.TemporaryDirectory() as tmp:
        stage = Path(tmp)
        for archive in [pack, *sorted(folder.glob("resume-*.tar"))]:
            with tarfile.open(archive) as tar:
                if hasattr(tarfile, "data_filter"):  # Python >= 3.11.4: no member may leave the stage
                    tar.extractall(stage, filter="data")
                else:
                    tar.extractall(stage)
        new, known, unfinished = 0, 0, []
        for run in run_dirs(stage):
            where = run.relative_to(stage)
            if (run / "eval.json").exists():
                if (committed / where / "eval.json").exists():
                    known += 1
                else:
                    copy_run(run, committed / where)
                    new += 1
            else:
                unfinished.append(where)
        resume = root / ".gpu" / "resume"
        fresh = root / ".gpu" / "resume.new"
        if fresh.exists():
            shutil.rmtree(fresh)
        fresh.mkdir(parents=True)
        for where in unfinished:
            copy_run(stage / where, fresh / where, checkpoint=True)
            copy_run(stage / where, logs / "partial" / where)
        if resume.exists():
            shutil.rmtree(resume)
        fresh.rename(resume)
        logs.mkdir(parents=True, exist_ok=True)
        for path in stage.iterdir():
            if path.is_file() and path.suffix in (".log", ".md"):
                shutil.copy2(path, logs / path.name)
        experiments = sorted(p.name.removesuffix(".sweep.json") for p in stage.glob("*.sweep.json"))
    with_checkpoint = sum((resume / w / CHECKPOINT).exists() for w in unfinished)
    print(f"{new} finished cell(s) new in {COMMITTED}, {known} already there; {len(unfinished)} unfinished run(s) "
          f"({with_checkpoint} with a checkpoint) in .gpu/resume for the next session, their logs in "
          f"{logs / 'partial'}; session logs in {logs}")
    for experiment in experiments:
        print(f"then: bati experiment {experiment} --scale paper --report-only --out-dir {COMMITTED}")
    print("then: bati claims")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", type=Path, default=ROOT, help="the checkout (default: this script's)")
    verbs = parser.add_subparsers(dest="verb", required=True)
    go = verbs.add_parser("away", help="pause the cpu queue, move results/ out, slim committed cells to .gpu/")
    go.add_argument("--stash", type=Path, default=None, help="where results/ goes (default: ../bati-results-away)")
    go.add_argument("--no-pause", action="store_true", help="leave the cpu queue running (it must not write)")
    verbs.add_parser("back", help="move results/ back and resume the cpu queue")
    take = verbs.add_parser("unpack", help="a GPU command's packs into results/paper/experiments and .gpu/resume")
    take.add_argument("folder", type=Path,
                      help="the folder copied back from the GPU machine (its results.tar.gz and resume-*.tar)")
    take.add_argument("--logs", type=Path, required=True, help="where the session's logs and partial runs go")
    args = parser.parse_args(argv)
    root = args.root.resolve()
    try:
        if args.verb == "away":
            away(root, args.stash or root.parent / "bati-results-away", pause=not args.no_pause)
        elif args.verb == "back":
            back(root)
        else:
            unpack(root, args.folder, args.logs if args.logs.is_absolute() else root / args.logs)
    except GpuLocalError as err:
        print(f"gpu_local {args.verb}: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
