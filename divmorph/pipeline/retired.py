"""Rules a run folder was once trained under that today's code no longer runs, and the one-time
migration of a run's ``run.json`` to today's keys (``divmorph migrate``).

A run records its profile in ``run.json``. Records of format 1 may lack keys added since, and some of their values select rules that were replaced: the migration
writes each key out explicitly, moves a replaced rule out of the configuration into the record's
``retired`` section (``{"transfer.observation_statistics": "learning"}``: what the stage really ran
under), and turns ``transfer.compare_scratch`` into the explicit ``transfer.arms``. The profile then
holds today's keys only, the record still says what ran, and a stage with a retired rule is never
trained on under today's rules by mistake (:func:`retired_changes` makes it a changed stage: a run
command stops with the keys listed until ``--redo`` retrains it).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

#: ``run.json`` format: 2 = every key of today's profile written out, replaced rules in ``retired``
RECORD_FORMAT = 2


@dataclass(frozen=True)
class RetiredRule:
    """A value of a profile key that selected a rule today's code no longer runs.

    :param key: ``section.name`` in the profile.
    :param value: the retired value.
    :param today: the value (and rule) today's code runs.
    :param kept: whether the key is still a profile key (only its retired value went) or gone whole.

    Every key here came after runs were first recorded, with a default that changed the rule: a
    format-1 record without it ran the retired rule.
    """

    key: str
    value: Any
    today: Any
    kept: bool

    @property
    def section(self) -> str:
        return self.key.split(".")[0]

    @property
    def name(self) -> str:
        return self.key.split(".")[1]


RETIRED_RULES: tuple[RetiredRule, ...] = (
    # the fine-tuned arms' observation statistics went on moving under inherited weights
    RetiredRule("transfer.observation_statistics", "learning", "frozen", kept=False),
    # Adam's eps: 1e-10 for the DivMorph-way arms, SB3's 1e-5 for the others
    RetiredRule("transfer.adam_eps", None, 1e-10, kept=True),
    # the parts an ablation does not divert trained at learngene_lr_scale
    RetiredRule("transfer.undiverted_lr_scale", None, 1.0, kept=True),
    # the HyperDistill student was told nothing of the task
    RetiredRule("hyperdistill.task_input", "none", "index", kept=False),
    # the HyperDistill student normalised with one VecNormalize of its own
    RetiredRule("hyperdistill.observation_statistics", "own", "teachers", kept=False),
)
#: keys no longer in the profile, and what replaces them (a profile that sets one is told)
REMOVED_KEYS: dict[str, str] = {
    **{r.key: f"it always runs {r.today!r}" for r in RETIRED_RULES if not r.kept},
    "transfer.compare_scratch": "list the arms instead (transfer.arms: [divmorph, scratch])",
}


def migrate_configuration(configuration: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """A format-1 configuration in today's keys, and the retired rules it ran under.

    :returns: ``(configuration, retired)``: ``retired`` maps ``section.name`` to the value that ran.
    """
    values = {k: (dict(v) if isinstance(v, dict) else v) for k, v in configuration.items()}
    retired: dict[str, Any] = {}
    for rule in RETIRED_RULES:
        section = values.get(rule.section)
        if not isinstance(section, dict):
            continue
        value = section.get(rule.name, rule.value)  # a record from before the key ran the retired rule
        if value == rule.value:
            retired[rule.key] = value
        if rule.kept:
            section[rule.name] = rule.today if value == rule.value else value
        else:
            section.pop(rule.name, None)
    transfer = values.get("transfer")
    if isinstance(transfer, dict) and "compare_scratch" in transfer:
        compare = transfer.pop("compare_scratch")
        if transfer.get("arms") is None:
            transfer["arms"] = ["divmorph", "scratch"] if compare else ["divmorph"]
    return values, retired


def migrate_record(record: dict[str, Any], command: str = "divmorph migrate") -> tuple[dict[str, Any], list[str]]:
    """A ``run.json`` record in today's format; unchanged when it already is.

    :returns: ``(record, changes)``: ``changes`` says, a line each, what the migration wrote.
    """
    if record.get("format") == RECORD_FORMAT:
        return record, []
    configuration, retired = migrate_configuration(record["configuration"])
    changes = [f"{key}: {value!r} (retired: today's rule is {_today(key)!r})" for key, value in retired.items()]
    old_arms = (record["configuration"].get("transfer") or {}).get("arms")
    if "compare_scratch" in (record["configuration"].get("transfer") or {}):
        arms = configuration["transfer"]["arms"]
        changes.append(
            f"transfer.compare_scratch -> transfer.arms: {arms}" if old_arms is None else "transfer.compare_scratch dropped (arms given)"
        )
    migrated = {
        "format": RECORD_FORMAT,
        **{k: v for k, v in record.items() if k != "format"},
        "configuration": configuration,
        "retired": {**record.get("retired", {}), **retired},
    }
    migrated["history"] = [
        *record.get("history", []),
        {"command": command, "time": time.strftime("%Y-%m-%d %H:%M:%S"), "migrated": changes},
    ]
    return migrated, changes


def _today(key: str) -> Any:
    return next(rule.today for rule in RETIRED_RULES if rule.key == key)


def format_problem(record: dict[str, Any], path: Any) -> str | None:
    """What is wrong with a record of another format (it names the command migrating it), or ``None``."""
    if record.get("format") == RECORD_FORMAT:
        return None
    return (
        f"{path} was written before divmorph 0.2 (record format {record.get('format', 1)}, today's {RECORD_FORMAT}): "
        f"`divmorph migrate {Path(path).parent}` rewrites it once in today's keys (the old record is kept beside it)"
    )


def retired_changes(record: dict[str, Any], stage: str) -> list[str]:
    """The retired rules ``stage`` of the run ran under, as changes to today's rules (the stage's own
    section: a stage built on it is retrained with it, by ``--redo``)."""
    return [
        f"{key}: {value!r} (a rule retired in divmorph 0.2) -> {_today(key)!r}"
        for key, value in record.get("retired", {}).items()
        if key.split(".")[0] == stage
    ]
