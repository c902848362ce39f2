"""The run directory of ``twinrl run``: every file and folder a loop reads or writes, named once.

Layout (``OUT/``)::

    loop.json            "kind": "run" and the run's settings (task, seed, config); a resume
                         must match them
    progress.json        the finished stages and the per-round records (records only: no stage
                         reads a decision back from it)
    dataset/             every real transition, recorded as it happens (``twinrl.real.dataset``)
    eval/                evaluation only, never read by a stage: the twin's secret (twin.json),
                         the evaluation records (evaluation.json), the oracle's training (oracle/)
    round<r>/            round r's artefacts (``RoundDir``; ``round.json`` says what it is)
    summary.json, final.mp4, report.md, returns.png, success.png    the outputs

The identified ``System`` of a round is ``round<r>/system.json`` in both loops. The cartpole
family's sysid also writes its fit's record (parameter table, loss) to ``round<r>/sysid.json``;
runs made before ``system.json`` kept the System there (or, older still, its parameters and
latency side by side), and ``RoundDir.identified_system`` reads those too, so they resume.
"""

from __future__ import annotations

import json
from pathlib import Path

from twinrl.loop.errors import LoopError

__all__ = ["RunDir", "RoundDir"]


class RoundDir:
    """Round ``r``'s directory, ``OUT/round<r>/``: its stages' artefacts."""

    def __init__(self, path: str | Path):
        self.path = Path(path)

    def __repr__(self) -> str:
        return f"RoundDir({str(self.path)!r})"

    def make(self) -> None:
        """Create the round's directory with ``round.json``, which says what it is."""
        self.path.mkdir(parents=True, exist_ok=True)
        if not self.record.exists():
            from twinrl.report import write_json

            write_json(self.record, {"kind": "round", "round": self.number})

    @property
    def record(self) -> Path:
        """``round.json``: what the directory is (``twinrl.loop.checkpoints``)."""
        return self.path / "round.json"

    @property
    def number(self) -> int:
        """The round's number ``r`` (``round<r>``)."""
        return int(self.path.name.removeprefix("round"))

    # -- the identified system
    @property
    def system(self) -> Path:
        """The identified ``System`` (``System.save``'s format)."""
        return self.path / "system.json"

    @property
    def sysid(self) -> Path:
        """The cartpole family's sysid record: the System, the parameter table, the fit's
        loss and cost (what the report draws)."""
        return self.path / "sysid.json"

    def identified_system(self, env_name: str):
        """The round's identified ``System``: ``system.json``, else what an older run kept in
        ``sysid.json`` (its ``system``, or older still its ``params`` and ``latency``)."""
        from twinrl.envs.system import FORMAT, System, SystemFormatError

        if self.system.exists():
            return System.load(self.system)
        path = self.sysid
        doc = json.loads(path.read_text())
        if "system" in doc:
            return System.from_json(doc["system"])
        try:
            return System.from_json({"format": FORMAT, "task": env_name, "params": doc["params"],
                                     "latency": int(doc["latency"])})
        except (KeyError, TypeError, ValueError, SystemFormatError) as e:
            raise LoopError(f"{path}: neither a 'system' nor the older 'params' and 'latency' "
                            f"({type(e).__name__}: {e}); start a new --out") from None

    @property
    def deploy_log(self) -> Path:
        """The deployment's finished episodes so far (``twinrl.loop.shared.EpisodeLog``)."""
        return self.path / "deploy_partial.json"

    # -- the cartpole family's artefacts
    @property
    def hybrid(self) -> Path:
        """The hybrid residual dynamics (``twinrl.sim2real.hybrid.save``)."""
        return self.path / "hybrid"

    @property
    def train(self) -> Path:
        """The policy learned in the identified simulator (``twinrl.learn.runner``)."""
        return self.path / "train"

    @property
    def train_metrics(self) -> Path:
        """The learner's per-epoch metrics (its learning curve, for the report)."""
        return self.train / "metrics.csv"

    @property
    def residual(self) -> Path:
        """The residual policy's checkpoint (all zeros when the gate rejected it)."""
        return self.path / "residual"

    def residual_metrics(self) -> dict | None:
        """The residual checkpoint's metrics (``accepted``, the gate's returns), or None when
        the round trained no residual."""
        f = self.residual / "checkpoint.json"
        return json.loads(f.read_text()).get("metrics", {}) if f.exists() else None

    # -- the SAM-RL family's artefacts
    @property
    def calibration(self) -> Path:
        """The hand-eye calibration and the tool's grasp."""
        return self.path / "calibration.json"

    @property
    def plans(self) -> Path:
        """The trajectory-optimised demonstrations (``twinrl.learn.plans.save``)."""
        return self.path / "plans.npz"

    @property
    def actor(self) -> Path:
        """The image actor (``twinrl.learn.runner``, algorithm ``imitation``)."""
        return self.path / "actor"

    @property
    def q(self) -> Path:
        """The sensing-aware Q (``twinrl.learn.runner``, algorithm ``sensing``)."""
        return self.path / "q"

    @property
    def q_summary(self) -> Path:
        """The Q's training summary (its held-out rank correlation: ``final.rank_corr``)."""
        return self.q / "summary.json"

    @property
    def camera_check(self) -> Path:
        """The deployment's camera and why: Q's rank against ``camera_min_rank``, and Q's choice
        against the default camera in the identified twin (``ArmLoopConfig.camera_check``)."""
        return self.path / "camera_check.json"


class RunDir:
    """A ``twinrl run`` output directory ``OUT`` (see the module docstring for its layout)."""

    def __init__(self, out: str | Path):
        self.out = Path(out)

    def __repr__(self) -> str:
        return f"RunDir({str(self.out)!r})"

    @property
    def settings(self) -> Path:
        return self.out / "loop.json"

    @property
    def progress(self) -> Path:
        return self.out / "progress.json"

    @property
    def dataset(self) -> Path:
        return self.out / "dataset"

    @property
    def eval(self) -> Path:
        """Evaluation only: no stage reads anything under it."""
        return self.out / "eval"

    @property
    def secret(self) -> Path:
        """The real twin's secret salt (``twinrl.real.remote.TwinClient``)."""
        return self.eval / "twin.json"

    @property
    def evaluation(self) -> Path:
        return self.eval / "evaluation.json"

    @property
    def oracle_policy(self) -> Path:
        return self.eval / "oracle"

    @property
    def summary(self) -> Path:
        return self.out / "summary.json"

    @property
    def video(self) -> Path:
        return self.out / "final.mp4"

    @property
    def success_plot(self) -> Path:
        return self.out / "success.png"

    def round(self, r: int) -> RoundDir:
        return RoundDir(self.out / f"round{r}")
