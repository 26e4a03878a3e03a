"""`socnav calibrate` (safety thresholds or a trigger chosen on calibration episodes), `socnav convert` (a policy
file to a Stable-Baselines3 model) and `socnav export` (a policy and its safety layer as an ONNX navigator).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer
from rich.markup import escape
from rich.table import Table

from socnav._console import console, fail
from socnav.cli.options import (
    ACTING_MODEL_HELP,
    SINGLE_AGENT_MAX_HUMANS_HELP,
    SINGLE_AGENT_N_HUMANS_HELP,
    SINGLE_AGENT_SCENARIO_HELP,
    config_option,
    episodes_option,
    estimator_option,
    force_option,
    humans_option,
    max_humans_option,
    mc_samples_option,
    members_option,
    model_option,
    n_humans_option,
    scenario_option,
    sensing_option,
)
from socnav.config import EnvConfig

if TYPE_CHECKING:  # pandas, torch and SB3 load inside the commands: `socnav --help` stays fast

    pass

from socnav.cli.common import (
    check_estimator_options,
    check_human_model,
    check_out_file,
    deprecated_alias,
    load_learned_policy,
    model_world,
    policy_and_estimator,
    progress_display,
    single_agent_env_config,
)

THRESHOLDS_OUT = Path("runs") / "calibration" / "thresholds.yaml"


def _calibration_report_path(out: Path) -> Path:
    """The report `save_calibration` writes next to the thresholds file `out` (every candidate and its scores)."""
    return out.with_suffix(".report.json")


#: Fewer calibration collisions than this and `socnav calibrate` warns that the prevented share is rough.
FEW_COLLISIONS = 10


def calibration_table(thresholds: Any, report: dict[str, Any], title: str) -> Table:
    """The chosen thresholds and their measured scores (`calibrate_thresholds` report) as one table row."""
    import math

    table = Table(title=title)
    for column in ("λ_ep", "λ_f", "λ_prox", "β1", "c_prox", "hold", "prevented", "collisions", "false act."):
        table.add_column(column, justify="right", no_wrap=True)
    values = thresholds.model_dump()
    table.add_row(*(f"{values[key]:.4g}" for key in ("lambda_ep", "lambda_feat", "lambda_prox", "beta1")),
                  values["proximity"], str(values["hold_steps"]),
                  "–" if math.isnan(report["prevented_fraction"]) else f"{report['prevented_fraction']:.0%}",
                  str(report["n_collisions"]),
                  f"{report['false_activation_rate']:.1%}"
                  + (f" (≤ {report['false_activation_upper']:.1%})" if "false_activation_upper" in report else ""))
    return table


def calibrate(
    model: str | None = model_option(ACTING_MODEL_HELP),
    estimator: str = estimator_option("mc"),
    members: str | None = members_option(),
    k: int = mc_samples_option(),
    scenario: str | None = scenario_option(None, help=SINGLE_AGENT_SCENARIO_HELP),
    n_humans: int | None = n_humans_option(SINGLE_AGENT_N_HUMANS_HELP),
    max_humans: int | None = max_humans_option(SINGLE_AGENT_MAX_HUMANS_HELP),
    config: Path | None = config_option(),
    episodes: int = episodes_option(40, help="episodes per calibration configuration"),
    false_activation_budget: float = typer.Option(
        0.05, min=0.0, max=1.0, help="allowed false-activation rate: the share of unperturbed steps on which the "
                                     "fallback may act (the experiment's safety.false_activation_budget)"),
    budget: float | None = typer.Option(None, "--budget", min=0.0, max=1.0, hidden=True,
                                           callback=deprecated_alias("--budget", "--false-activation-budget"),
                                           help="deprecated name of --false-activation-budget"),
    proximity: str = typer.Option("both", help="c_prox readings to search: both | abs-relative-speed | closing-speed"),
    sensing: str = sensing_option("perceived", help="what the proximity terms and fallback read: perceived (the "
                                                    "noisy observation) | true (the simulator's state)"),
    confidence: float = typer.Option(0.95, min=0.5, max=0.999, help="the budget must hold at this one-sided "
                                                                     "confidence (0.5: the point estimate)"),
    out: Path = typer.Option(THRESHOLDS_OUT, help="threshold file (.yaml/.json)"),
    humans: str | None = humans_option(),
    force: bool = force_option("the --out threshold file (and its report)"),
    trigger: str = typer.Option("paper", help="what decides the hand-over: the rule (paper | proximity-only | "
                                              "uncertainty-only) or a score trigger (time-to-collision | closing-gap "
                                              "| predicted-clearance | conformal | risk-model | "
                                              "risk-model+uncertainty; docs/uncertainty-safety.md)"),
) -> None:
    """Choose the safety thresholds on calibration episodes (perturbations and seeds disjoint from evaluation)."""
    from socnav.safety import PROXIMITY_VARIANTS, calibrate_thresholds, save_calibration
    from socnav.safety.rule import RULE_CONDITIONS

    false_activation_budget = budget if budget is not None else false_activation_budget
    _check_trigger_name(trigger)
    if proximity != "both" and proximity not in PROXIMITY_VARIANTS:
        fail(f"--proximity {proximity!r} is not known; allowed: both, {', '.join(PROXIMITY_VARIANTS)}")
    if sensing not in ("perceived", "true"):
        fail(f"--sensing {sensing!r} is not known; allowed: perceived, true")
    if out.is_dir() or out.suffix not in (".yaml", ".yml", ".json"):
        fail(f"--out must be a .yaml or .json file path, got {str(out)!r}")
    check_out_file("--out", out, force=force, create_parent=out == THRESHOLDS_OUT)
    check_out_file("--out", _calibration_report_path(out), force=force, create_parent=out == THRESHOLDS_OUT)
    if trigger.startswith("risk-model"):
        from socnav.safety.calibration.trigger_search import risk_model_path

        check_out_file("--out", risk_model_path(out.parent, trigger, f"{out.stem}."), force=force,
                        create_parent=out == THRESHOLDS_OUT)
    check_estimator_options(estimator, model, members)  # before a model loads
    check_human_model(humans)
    env_config = model_world(model, scenario, config, n_humans, max_humans,
                              default=lambda: single_agent_env_config(scenario, config, n_humans, max_humans,
                                                                       humans),
                              humans=humans)
    policy, uncertainty = policy_and_estimator(estimator, model, members, k, env_config)
    if trigger not in RULE_CONDITIONS:
        _calibrate_score_trigger(trigger, policy, uncertainty, env_config, episodes, false_activation_budget,
                                 sensing, confidence, out)
        return
    with progress_display() as progress:
        task = progress.add_task("calibration episodes (collect, then replay each candidate)", total=None)
        thresholds, report = calibrate_thresholds(
            policy, None if trigger == "proximity-only" else uncertainty, env_config.model_dump(mode="json"), episodes,
            false_activation_budget, proximity, confidence=confidence,
            progress=lambda done, total: progress.update(task, completed=done, total=total), sensing=sensing,
            conditions=trigger)
    report_path = save_calibration(thresholds, report, out)
    console.print(calibration_table(thresholds, report, f"calibrated thresholds ({estimator}, false-activation "
                                                        f"budget {false_activation_budget:.0%})"))
    console.print("prevented: share of the plain policy's calibration collisions prevented in the replayed episodes "
                  "(mean over perturbation types); false act.: share of unperturbed steps where the fallback acted "
                  f"(≤ its one-sided {confidence:.0%} upper bound); every candidate in "
                  f"{escape(str(report_path))}", highlight=False)
    if report["n_collisions"] and report["n_collisions"] < FEW_COLLISIONS:
        console.print(f"[yellow]warning:[/] the prevented share rests on only {report['n_collisions']} calibration "
                      f"collision(s) (< {FEW_COLLISIONS}); it is a rough estimate: use more --episodes",
                      highlight=False)
    if "note" in report:
        console.print(escape(report["note"]), highlight=False)
    console.print(f"thresholds: {out}  (use with --safety {out})")


def _check_trigger_name(trigger: str) -> None:
    """`--trigger`: a registered trigger or ``risk-model+uncertainty`` (did-you-mean otherwise)."""
    from socnav.safety.triggers import TriggerError, trigger_class, trigger_names

    if trigger in (*trigger_names(), "risk-model+uncertainty"):
        return
    try:
        trigger_class(trigger)
    except TriggerError as exc:
        fail(f"--trigger: {exc}")


def _calibrate_score_trigger(trigger: str, policy: Any, uncertainty: Any, env_config: EnvConfig, episodes: int,
                             budget: float, sensing: str, confidence: float, out: Path) -> None:
    """`calibrate --trigger NAME` of a score trigger: prepared (the conformal bound fitted, the risk model trained
    on its own seeds), its threshold chosen by replays, written to `out` (with the risk model beside it)."""
    from socnav.safety.calibration.trigger_search import calibrate_score_triggers, prepare_triggers
    from socnav.safety.triggers import save_trigger_spec

    env = env_config.model_dump(mode="json")
    n_envs = min(episodes, 40)
    notes: list[str] = []
    with console.status("calibration episodes (prepare, record, then replay each candidate)") as status:
        def log(message: str) -> None:
            notes.append(message)
            status.update(message)

        specs = prepare_triggers([trigger], policy, uncertainty, env, episodes, 3 * episodes, sensing, 4, n_envs,
                                 out.parent, log, prefix=f"{out.stem}.")
        if trigger not in specs:
            fail(f"--trigger {trigger}: {notes[-1]}")
        chosen = calibrate_score_triggers(specs, policy, uncertainty, env, episodes, [budget], sensing, 4, n_envs,
                                          confidence, log)[trigger][budget]
    save_trigger_spec(chosen, out, extra={"false_activation_budget": budget, "confidence": confidence,
                                          "episodes_per_configuration": episodes})
    state = "never fires: no threshold kept the budget" if chosen.threshold == float("inf") else (
        f"threshold {chosen.threshold:.4g}")
    console.print(f"{trigger}: {state} (false-activation budget {budget:.0%} at {confidence:.0%} confidence)",
                  highlight=False)
    console.print(f"trigger: {out}  (use with --safety {out})", highlight=False)


def convert(
    model: str = typer.Argument(..., help="socnav policy file (from socnav train), or 'pretrained' / "
                                          "'pretrained-maps' / 'pretrained-ppo'"),
    to_sb3: Path = typer.Option(..., "--to-sb3", help="write a Stable-Baselines3 model zip here "
                                                       "(ODVPPO.load reads it)"),
    force: bool = force_option("the --to-sb3 file"),
) -> None:
    """Turn a socnav policy file into a full Stable-Baselines3 model (for fine-tuning with model.learn)."""
    from socnav.rl.convert import to_sb3 as convert_to_sb3
    from socnav.rl.persistence import PolicyLoadError

    if to_sb3.suffix != ".zip":
        fail(f"--to-sb3 must be a .zip path, got {to_sb3.name!r}")
    check_out_file("--to-sb3", to_sb3, force=force)
    try:
        sb3_model = convert_to_sb3(model, n_envs=1)
    except PolicyLoadError as exc:
        fail(str(exc))
        return
    to_sb3.parent.mkdir(parents=True, exist_ok=True)
    sb3_model.save(to_sb3)
    console.print(f"SB3 model: {escape(str(to_sb3))}  (from socnav.rl import ODVPPO; ODVPPO.load({str(to_sb3)!r}, "
                  "env=...); SB3's format is pickled: load only files you trust)", highlight=False)


def export(
    model: str = typer.Argument(..., help="policy file (socnav train's model.zip) or 'pretrained' / "
                                          "'pretrained-maps' / 'pretrained-ppo'"),
    out: Path = typer.Option(Path("navigator.onnx"), help="the ONNX navigator file to write"),
    thresholds: str = typer.Option("mc", help="safety thresholds: mc | ensemble | a `socnav calibrate` FILE (a "
                                              "trigger file too: the navigator then decides with that trigger)"),
    # k, p-test and window are read as text and checked by socnav.export.check_settings: one line naming the
    # option and its allowed range (socnav.runtime.format's MAX_K, MAX_WINDOW) for any bad value, 1e9 included.
    # typer does not enforce min / max on text: they document the range (docs/configuration_table.py reads them).
    k: str = typer.Option("20", min=2, max=1000, metavar="INTEGER", help="MC-dropout samples per decision"),
    p_test: str | None = typer.Option(None, metavar="FLOAT", help="MC-dropout p, in (0, 1) (default: the "
                                                                     "policy's; 0 would disable the uncertainty)"),
    window: str = typer.Option("4", min=1, max=10_000, metavar="INTEGER", help="uncertainty window in steps"),
    value: bool = typer.Option(False, "--value", help="also export the critic (output 'value')"),
    force: bool = force_option("the --out navigator file"),
) -> None:
    """Export a policy, its MC-dropout settings and safety thresholds as ONNX for the torch-free socnav.runtime."""
    import importlib.util

    from socnav.extras import install_hint

    missing = [name for name in ("onnx", "onnxruntime") if importlib.util.find_spec(name) is None]
    if missing:
        fail(f"socnav export needs {' and '.join(missing)}: {install_hint('export')}")
    from socnav.export import ExportError, check_settings, export_onnx
    from socnav.safety import ThresholdsError
    from socnav.safety.triggers import TriggerError, load_safety

    try:
        k_value, p_test_value, window_value = check_settings(
            k, p_test, window, names={"k": "--k", "p_test": "--p-test", "window": "--window"})
    except ExportError as exc:
        fail(str(exc))
    check_out_file("--out", out, force=force)
    if Path(thresholds).is_dir():
        fail(f"--thresholds {thresholds} is a directory; name a thresholds file (from socnav calibrate) or a preset: "
             "mc, ensemble")
    try:  # before the policy loads
        load_safety(thresholds)
    except (ThresholdsError, TriggerError, OSError) as exc:
        fail(f"--thresholds: {exc}")

    policy = load_learned_policy(model)
    try:
        path = export_onnx(policy, out, thresholds=thresholds, k=k_value, p_test=p_test_value, window=window_value,
                           with_value=value)
    except (ExportError, ThresholdsError, TriggerError, OSError) as exc:
        fail(str(exc))
    console.print(f"navigator: {path}  (run it with socnav.runtime.SafeNavigator.load({str(path)!r}))")

