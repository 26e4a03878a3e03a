"""Shared test settings: a small, deterministic hypothesis profile so the suite stays fast in CI, `require`
(`tests/_extras.py`), which fails a test whose optional package is missing instead of skipping it, and the `slow`
marker of the tests in `SLOW_TESTS`.

The quick tier leaves out the slow and the heavy tests::

    python -m pytest -n 2 -m "not slow and not heavy"
"""

import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

# Test modules import helpers of this directory (`from _extras import require`) whatever pytest's import mode.
if str(Path(__file__).parent) not in sys.path:
    sys.path.insert(0, str(Path(__file__).parent))

settings.register_profile(
    "socnav", max_examples=25, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow]
)
settings.load_profile("socnav")


#: The tests that took more than `SLOW_THRESHOLD_S` (setup, call and teardown together) in one run of the whole
#: suite (`pytest --durations=0 -n 2` on 2 cores; the time measured is noted after each), heavy ones aside: marked
#: `slow`, left out of the quick tier. A name with its parameters (``[...]``) marks that case alone; a test's first
#: case often bears its worker's one-time warm-up (imports, numba's cache), and the cost moves with it. Tests sharing
#: a module fixture that takes long to build are listed together (test_runner.py's `local_run`: 23 s).
SLOW_THRESHOLD_S = 1.0
SLOW_TESTS: dict[str, tuple[str, ...]] = {
    "tests/rl/test_open_plane_dagger_script.py": ("test_a_tiny_dagger_run_saves_a_policy_with_its_feature_range",
                                                  "test_worlds_share_the_labels_and_the_first_names_the_policy"),
    "tests/paper/test_safety_benchmark_page.py": (
        "test_the_section_across_training_seeds_is_kept_to_the_end_of_the_page",),  # 1.7 s: the script's imports
    "tests/rl/test_maps_policy_script.py": ("test_clone_dagger_then_continue",  # 18.8 s
                                            "test_dagger_rounds_are_saved_and_a_later_run_continues_after_the_last",
                                            "test_dagger_from_a_start_with_the_safety_layer_driving"),  # 28.7 s
    "tests/rl/test_heading_frame.py": ("test_a_heading_frame_policy_trains_saves_loads_and_exports",),  # 1.8 s
    "tests/rl/test_imitation.py": ("test_a_cloned_policy_acts_like_its_teacher",),  # 2.0 s
    "tests/sim/test_scan_people.py": ("test_each_beam_reads_the_nearer_of_the_wall_and_the_first_person",),  # 9.0 s
    "tests/envs/test_actions_and_counts.py": (
        "test_nan_action_is_refused_naming_the_environment_and_changes_nothing",  # 8.6 s
        "test_the_memory_estimate_matches_what_environments_take[config1]",  # 1.0 s
    ),
    "tests/envs/test_env_api.py": (
        "test_gymnasium_checker_passes[corridor]",  # 10.6 s
    ),
    "tests/envs/test_perturbations.py": (
        "test_env_with_the_behaviour_shift_plays_social_force_humans",  # 1.1 s
    ),
    "tests/experiments/test_report.py": (
        "test_paper_table_holds_the_spec_excerpt",  # 1.2 s
        "test_partial_run_is_reported_and_left_out",  # 2.6 s
        "test_report_command",  # 1.3 s
        "test_sections_are_registered_per_experiment_kind",  # 2.0 s
        "test_table1_intervals_aggregate_and_verdicts",  # 3.7 s
        "test_table1_numbers_equal_a_direct_computation",  # 3.2 s
        "test_training_curves_mean_and_band_over_seeds",  # 2.5 s
    ),
    "tests/experiments/test_kinds.py": (
        "test_every_shipped_kind_registers_its_planner_executors_and_page[table1-table1]",  # 1.3 s: the first import
    ),
    "tests/experiments/test_runner.py": (
        "test_corrupt_and_half_written_units_are_redone",  # 0.0 s
        "test_local_backend_end_to_end",  # 0.0 s
        "test_ray_backend_end_to_end",  # 12.5 s
        "test_running_units_report_their_progress_from_the_worker",  # 23.2 s
        "test_tune_runs_trials_and_writes_a_preset",  # 4.0 s
    ),
    "tests/paper/test_uncertainty_report.py": (
        "test_behaviour_shift_is_a_column_of_ours_in_tables_2_and_3_and_not_in_the_papers_claims",  # 1.8 s
        "test_sections_skip_missing_records_and_unfinished_units",  # 2.3 s
        "test_table2_numbers_bold_and_dashes",  # 1.4 s
    ),
    "tests/paper/test_uncertainty_units.py": (
        "test_a_tiny_behaviour_shift_experiment_runs_with_social_force_humans",  # 2.8 s
        "test_ablation_safety_units_play_every_rule_on_the_same_episodes",  # 2.8 s
        "test_both_sensings_are_calibrated_and_evaluated",  # 1.6 s
        "test_proximity_only_calibration_unit_writes_every_budget_without_an_estimator",  # 19.0 s
        "test_tiny_uncertainty_experiment_runs_end_to_end",  # 26.8 s
    ),
    "tests/rl/test_scan_policy.py": (
        "test_scan_environment_passes_the_env_checkers",  # 1.5 s
    ),
    "tests/rl/test_training.py": (
        "test_same_seed_gives_the_same_training_run",  # 1.8 s
        "test_train_writes_run_directory_and_loadable_model",  # 1.4 s
    ),
    "tests/rl/test_untrusted.py": (
        "test_rerun_of_a_sweep_never_executes_a_planted_checkpoint",  # 1.0 s
    ),
    "tests/ros2/test_extra.py": (
        "test_nothing_but_the_ros2_commands_imports_rclpy",  # 2.6 s
    ),
    "tests/runtime/test_equivalence.py": (
        "test_mc_dropout_samples_and_uncertainty_match_torch",  # 3.0 s
    ),
    "tests/runtime/test_pretrained_maps.py": (
        "test_the_exported_map_navigator_decides_as_its_safety_layer",  # 1.3 s
    ),
    "tests/runtime/test_navigator.py": (
        "test_example_control_loop_runs_without_torch",  # 1.2 s
        "test_import_socnav_imports_no_torch",  # 1.1 s
        "test_navigator_reproduces_safe_policy_episodes[circle_crossing-5-1-0-paper]",  # 1.2 s
        "test_runtime_imports_no_torch",  # 1.4 s
    ),
    "tests/safety/test_assembly.py": (
        "test_ensemble_layer_decides_as_the_one_built_by_hand",  # 3.5 s
        "test_evaluate_safety_plays_the_assembled_layer",  # 1.2 s
        "test_mc_layer_decides_as_the_one_built_by_hand",  # 1.8 s
    ),
    "tests/safety/test_rule_variants.py": (
        "test_a_light_budget_proposes_at_the_budget_alone_and_is_not_refined",  # 2.8 s
        "test_calibrate_budgets_replays_each_rule_once_and_matches_single_budget_calibrations",  # 7.7 s
    ),
    "tests/safety/test_safety.py": (
        "test_calibrate_thresholds_replays_the_plain_policy_once_and_fills_the_bar",  # 1.6 s
        "test_select_by_rollouts_maximises_measured_prevention_within_the_budget",  # 1.2 s
    ),
    "tests/safety/test_sensing.py": (
        "test_calibrated_thresholds_carry_the_sensing_they_were_calibrated_with",  # 1.5 s
    ),
    "tests/sim/test_geometry.py": (
        "test_line_of_sight_through_a_door",  # 1.6 s
    ),
    "tests/sim/test_orca.py": (
        "test_invariants",  # 2.4 s
    ),
    "tests/sim/test_replay_and_mix.py": (
        "test_humans_follow_their_tracks_and_enter_and_leave",  # 2.5 s
        "test_the_shares_over_many_episodes_match_the_configured_ones",  # 1.2 s
    ),
    "tests/sim/test_social_force.py": (
        "test_defaults_are_pysocialforces_published_ones",  # 1.1 s
        "test_fifty_step_trajectories_match_pysocialforce[0]",  # 1.0 s
        "test_one_step_matches_pysocialforce_on_random_crowds[0]",  # 8.2 s
    ),
    "tests/sim/test_social_force_walls.py": (
        "test_humans_walking_at_a_wall_do_not_pass_through_it",  # 1.5 s
    ),
    "tests/sim/test_walls_world.py": (
        "test_map_scenarios_pass_the_checkers_and_start_clear_of_the_walls[corridor]",  # 1.2 s
        "test_map_scenarios_pass_the_checkers_and_start_clear_of_the_walls[doorway]",  # 1.4 s
    ),
    "tests/sim/test_world.py": (
        "test_noise_off_means_no_change",  # 1.4 s
    ),
    "tests/test_cli.py": (
        "test_calibrate_writes_a_threshold_file_that_animate_uses",  # 35.1 s
        "test_demo_writes_tables_and_animation",  # 4.9 s
    ),
    "tests/test_new_user_errors.py": (
        "test_an_address_where_no_ray_answers_gives_up_within_the_timeout",  # 20.0 s
    ),
    "tests/test_untrusted_paths.py": (
        "test_train_api_refuses_a_directory_holding_a_run_and_force_moves_it_aside",  # 1.9 s
    ),
    "tests/test_usability.py": (
        "test_animate_mentions_the_fallback_only_with_a_safety_layer",  # 3.4 s
        "test_animate_plays_a_trigger_file_as_its_safety_layer",  # 2.5 s
        "test_calibrate_shows_progress_and_warns_about_few_collisions",  # 46.2 s
        "test_piped_tables_keep_words_whole",  # 3.9 s
        "test_python_m_socnav_version_and_help_without_type_noise",  # 1.1 s
        "test_tune_continued_study_explores_and_refuses_other_settings",  # 4.9 s
    ),
    "tests/uncertainty/test_estimators.py": (
        "test_mc_invariants",  # 1.2 s
    ),
}


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark `slow` the tests `SLOW_TESTS` lists (by module path and test name, with or without its parameters)."""
    slow = pytest.mark.slow
    for item in items:
        path, _, name = item.nodeid.partition("::")
        listed = SLOW_TESTS.get(path, ())
        if name in listed or name.split("[")[0] in listed:
            item.add_marker(slow)
