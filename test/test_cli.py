"""The ``skidkin`` command end to end: calibrate -> parameters file -> predict == the real node."""

import argparse
import csv
import os
from pathlib import Path
import stat

import numpy as np
import pytest
from skidkin_ros.adapters.sim_writer import write_truth_csv
from skidkin_ros.cli import cmd_demo
from skidkin_ros.cli.main import main
from skidkin_ros.core.drive import WheelSamples
from skidkin_ros.core.odometry.config import OdometryConfig, read_params_file, write_params_file
from skidkin_ros.sim.simulate import SimConfig, simulate

HUSKY = Path(__file__).resolve().parents[1] / 'data' / 'husky' / 'drive_husky_windows.csv'


@pytest.fixture(scope='module')
def sim_table(tmp_path_factory):
    folder = tmp_path_factory.mktemp('sim')
    sim = simulate(SimConfig(duration_s=90.0, seed=5))
    return write_truth_csv(sim, folder / 'drive.csv'), sim


def _read_csv(path):
    with open(path, newline='') as handle:
        rows = list(csv.DictReader(handle))
    return rows


def test_calibrate_then_predict_then_the_real_node_agrees(sim_table, tmp_path, capsys):
    table, sim = sim_table
    params = tmp_path / 'params.yaml'
    # roc's beta_2 may end on its clamp on this exact data: a warning, exit 0
    assert main(['calibrate', str(table), '--out', str(params), '--robot', 'sim']) == 0
    out = capsys.readouterr().out
    assert '<- best' in out and 'edd_asymmetric' in out
    config = OdometryConfig.from_flat(read_params_file(params))
    # The simulator samples the wheel speeds at their stamps: the trapezoid is the exact rule,
    # and calibrate finds it on the held-out data and writes it.
    assert config['interval'] == 'midpoint' and 'midpoint  ' in out and '<- written' in out
    truth = sim.config.true_params
    fitted = config.model_values['edd_asymmetric']
    for name in ('alpha_l', 'alpha_r', 'y_l', 'y_r'):
        assert fitted[name] == pytest.approx(truth[name], abs=0.03), name
    assert config.active_noise is not None  # the covariance is calibrated

    pred_csv = tmp_path / 'pred.csv'
    assert main(['predict', str(table), '--params', str(params), '--out', str(pred_csv)]) == 0
    rows = _read_csv(pred_csv)
    assert len(rows) == len(sim.wheels) and 'pred_yaw' in rows[0] and 'x' in rows[0]

    from skidkin_ros.node.replay import replay_through_node
    wheels = WheelSamples(sim.wheels.t_ns - sim.wheels.t_ns[0], sim.wheels.omega_l,
                          sim.wheels.omega_r)
    replay = replay_through_node(wheels, params_file=params)
    predicted = {int(round(float(r['t']) * 1e9)): (float(r['pred_x']), float(r['pred_y']),
                                                   float(r['pred_yaw'])) for r in rows}
    node = dict(zip((int(t) for t in replay.t_ns), replay.poses))
    common = sorted(set(predicted) & set(node))
    assert len(common) >= len(rows) - 2
    diff = max(np.abs(np.array(predicted[t]) - node[t]).max() for t in common)
    assert diff < 1e-5  # the CSV holds 6 decimals; the node and predict share the integrator


def test_predict_names_the_file_model_and_accepts_another(sim_table, tmp_path):
    table, _ = sim_table
    params = tmp_path / 'p.yaml'
    assert main(['calibrate', str(table), '--out', str(params), '--models', 'edd_symmetric']) == 0
    first, second = tmp_path / 'a.csv', tmp_path / 'b.csv'
    assert main(['predict', str(table), '--params', str(params), '--out', str(first)]) == 0
    assert main(['predict', str(table), '--params', str(params), '--model', 'ideal_dd',
                 '--out', str(second)]) == 0
    a, b = _read_csv(first), _read_csv(second)
    assert a[-1]['pred_x'] != b[-1]['pred_x']


def test_rerun_gives_the_same_parameters(sim_table, tmp_path):
    table, _ = sim_table
    runs = []
    for name in ('one.yaml', 'two.yaml'):
        assert main(['calibrate', str(table), '--out', str(tmp_path / name)]) == 0
        flat = read_params_file(tmp_path / name)
        runs.append({k: v for k, v in flat.items() if not k.startswith('provenance.date')})
    assert runs[0] == runs[1]  # C20


def test_existing_output_is_kept_without_force(sim_table, tmp_path, capsys):
    table, _ = sim_table
    params = tmp_path / 'params.yaml'
    params.write_text('precious')
    assert main(['calibrate', str(table), '--out', str(params)]) == 5  # C18
    assert params.read_text() == 'precious'
    assert '--force' in capsys.readouterr().err


def test_missing_source_is_a_clear_error(tmp_path, capsys):
    code = main(['calibrate', str(tmp_path / 'nowhere_bag'), '--out', str(tmp_path / 'p.yaml')])
    assert code == 3  # C1
    err = capsys.readouterr().err
    assert 'nowhere_bag' in err and 'Traceback' not in err
    assert not (tmp_path / 'p.yaml').exists()


def test_straight_driving_only_refuses_to_write_what_it_cannot_observe(tmp_path, capsys):
    sim = simulate(SimConfig(duration_s=80.0, seed=1, script=(
        (20.0, 4.0, 4.0), (20.0, -4.0, -4.0), (20.0, 4.0, 4.0))))
    table = write_truth_csv(sim, tmp_path / 'straight.csv')
    params = tmp_path / 'p.yaml'
    code = main(['calibrate', str(table), '--out', str(params)])
    err = capsys.readouterr().err
    assert code == 4  # C14: no turning, the yaw parameters are not observable
    assert 'b_hat' in err or 'not observable' in err or 'unobservable' in err
    assert not params.exists()


@pytest.mark.skipif(not HUSKY.exists(), reason='shared Husky data not present')
def test_husky_calibration_from_the_command_line(tmp_path, capsys):
    params = tmp_path / 'husky.yaml'
    assert main(['calibrate', str(HUSKY), '--split-by', 'calib_step', '--wheel-radius',
                 '0.1651', '--track-width', '0.555', '--out', str(params),
                 '--report', str(tmp_path / 'report')]) == 0
    out = capsys.readouterr().out
    config = OdometryConfig.from_flat(read_params_file(params))
    ratio = config.model_values['edd_symmetric']['b_hat'] / 0.555
    assert 1.9 < ratio < 2.4  # Clearpath ships 1.875
    assert 'wheel_separation_multiplier' in out
    assert (tmp_path / 'report' / 'report.md').exists()
    assert main(['evaluate', str(HUSKY), '--params', str(params)]) == 0
    rows = {line.split()[0]: line.split() for line in capsys.readouterr().out.splitlines()
            if line.split() and line.split()[0] in config.model_values}
    assert float(rows[config.model][1]) < 0.5 * float(rows['ideal_dd'][1])  # median eps_t


def test_the_product_command_lists_the_product_and_the_lab_the_studies(capsys):
    from lab.cli.main import main as lab_main
    with pytest.raises(SystemExit):
        main(['--help'])
    product = capsys.readouterr().out
    for command in ('calibrate', 'evaluate', 'predict', 'diagnose', 'groundtruth', 'simulate',
                    'models', 'demo'):
        assert f'    {command} ' in product, command
    for study in ('effects', 'estimate', 'imu-study'):
        assert f'    {study} ' not in product, study
        with pytest.raises(SystemExit) as info:
            main([study])
        assert info.value.code == 2  # not a product command
    capsys.readouterr()
    with pytest.raises(SystemExit):
        lab_main(['--help'])
    lab = capsys.readouterr().out
    assert all(f'    {study} ' in lab for study in ('effects', 'estimate', 'imu-study'))


def test_models_table_is_generated_from_the_specs(capsys):
    assert main(['models']) == 0
    out = capsys.readouterr().out
    assert '`models.edd_asymmetric.y_r`' in out and '(-inf, 0)' in out


def test_docs_model_table_matches_the_specs(capsys):
    page = (Path(__file__).resolve().parents[1] / 'docs' / 'models.md').read_text()
    main(['models'])
    assert capsys.readouterr().out.strip() in page, 'run `make docs` (skidkin models)'


@pytest.mark.heavy
def test_demo_pipeline_sized_down(tmp_path):
    args = argparse.Namespace(out=tmp_path / 'demo', force=False, train_duration=60.0,
                              eval_duration=40.0, eval_drives=2, no_cache=True,
                              progress=False)
    summary = cmd_demo.pipeline(args)
    assert summary['params'].exists()
    truth, icp = summary['true_params'], summary['fitted_icp']
    for name in ('alpha_l', 'alpha_r', 'y_l', 'y_r'):
        assert icp[name] == pytest.approx(truth[name], abs=0.05), name
    assert summary['node_vs_predict'] < 1e-9
    assert summary['node_vs_predict_covariance'] == 0.0  # one code path: bit for bit
    node_t, _ = summary['node_eps']
    ideal_t, _ = summary['ideal_eps']
    assert np.median(node_t) < 0.25 * np.median(ideal_t)


def test_diagnose_from_the_command_line_on_two_cores(tmp_path, capsys):
    """Calibrate, then diagnose a drive with an undeclared skid: the file names it, both ways."""
    from skidkin_ros.sim.effects import make_effect
    tables = []
    for seed in (8, 9, 10):
        sim = simulate(SimConfig(duration_s=90.0, seed=seed, true_model='edd_symmetric',
                                 true_params={'alpha': 0.9, 'b_hat': 0.85},
                                 effects=(make_effect('lateral_skid', 0.1),)))
        tables.append(str(write_truth_csv(sim, tmp_path / f'skid{seed}.csv')))
    train, evaluate = tables[:2], tables[2]
    params = tmp_path / 'params.yaml'
    assert main(['calibrate', *train, '--out', str(params), '--models', 'edd_symmetric']) == 0
    outputs = {}
    for jobs in ('2', '1'):
        out = tmp_path / f'augmented_{jobs}.yaml'
        assert main(['diagnose', *train, '--eval', evaluate, '--params', str(params),
                     '--out', str(out), '--candidates', 'time_offset', 'lateral_skid',
                     'speed_slip', '--jobs', jobs, '--no-progress']) == 0
        outputs[jobs] = read_params_file(out)
        assert 'added lateral_skid' in capsys.readouterr().out
    config = OdometryConfig.from_flat(outputs['2'])
    assert config.model == 'augmented' and 'lateral_skid' in config.augmented_extensions
    # The number of processes does not change the result (only when it ran, and how long).
    stamps = ('provenance.date', 'provenance.seconds')
    assert {k: v for k, v in outputs['2'].items() if k not in stamps} == {
        k: v for k, v in outputs['1'].items() if k not in stamps}
    # An existing output is kept without --force (C18), and a bad --jobs is refused up front.
    before = (tmp_path / 'augmented_2.yaml').read_bytes()
    assert main(['diagnose', *train, '--params', str(params), '--out',
                 str(tmp_path / 'augmented_2.yaml')]) == 5
    assert (tmp_path / 'augmented_2.yaml').read_bytes() == before
    with pytest.raises(SystemExit):
        main(['diagnose', *train, '--params', str(params), '--out', str(tmp_path / 'x.yaml'),
              '--jobs', '0'])
    assert 'expected a whole number of processes >= 1' in capsys.readouterr().err


def test_output_errors_exit_5_before_any_work_without_a_traceback(sim_table, tmp_path, capsys):
    """C23: these escaped as tracebacks with exit code 1."""
    table, _ = sim_table
    params = tmp_path / 'params.yaml'
    write_params_file(params, {})
    folder = tmp_path / 'a_folder'
    folder.mkdir()
    existing = tmp_path / 'a_file.txt'
    existing.write_text('precious')
    missing = str(tmp_path / 'missing.csv')  # reached only if the output check came too late
    cases = [
        (['predict', str(table), '--params', str(params), '--out', str(folder), '--force'],
         'is a folder'),
        (['predict', str(table), '--params', str(params), '--out', '/proc/pred.csv'],
         'cannot write in folder /proc'),
        (['predict', str(table), '--params', str(params), '--out', str(tmp_path / ('p' * 300))],
         'longer than the file system takes'),
        (['predict', str(table), '--params', str(params), '--out', str(existing / 'p.csv')],
         'is not a folder'),
        (['calibrate', missing, '--out', '/proc/params.yaml'], 'cannot write in folder /proc'),
        (['calibrate', missing, '--out', str(tmp_path / 'p.yaml'), '--report', str(existing)],
         'is not a folder'),
        (['evaluate', missing, '--params', str(params), '--report', str(existing)],
         'is not a folder'),
        (['demo', '--out', str(existing)], 'is not a folder'),
        (['simulate', '--out', str(tmp_path / 'bag'), '--truth', '/proc/truth.csv'],
         'cannot write in folder /proc'),
    ]
    for argv, needle in cases:
        assert main(argv) == 5, argv
        err = capsys.readouterr().err
        assert needle in err and 'Traceback' not in err, (argv, err)
    assert existing.read_text() == 'precious' and list(folder.iterdir()) == []


def test_outputs_honour_the_umask_and_a_replaced_file_keeps_its_mode(sim_table, tmp_path):
    """C24: every output was created 0600, and --force made a 0644 file 0600."""
    table, _ = sim_table
    params = tmp_path / 'params.yaml'
    old_mask = os.umask(0o022)
    try:
        write_params_file(params, {})
        assert stat.S_IMODE(params.stat().st_mode) == 0o644
        out = tmp_path / 'pred.csv'
        assert main(['predict', str(table), '--params', str(params), '--out', str(out)]) == 0
        assert stat.S_IMODE(out.stat().st_mode) == 0o644
        out.chmod(0o640)
        assert main(['predict', str(table), '--params', str(params), '--out', str(out),
                     '--force']) == 0
        assert stat.S_IMODE(out.stat().st_mode) == 0o640
        os.umask(0o077)
        private = tmp_path / 'private.csv'
        assert main(['predict', str(table), '--params', str(params), '--out', str(private)]) == 0
        assert stat.S_IMODE(private.stat().st_mode) == 0o600
    finally:
        os.umask(old_mask)


def test_demo_force_removes_only_what_the_demo_wrote(tmp_path, capsys):
    """C23: --force on a folder of the user's files deleted them all (shutil.rmtree)."""
    out = tmp_path / 'mine'
    out.mkdir()
    (out / 'thesis.tex').write_text('precious')
    assert main(['demo', '--out', str(out), '--force']) == 5
    assert 'did not write' in capsys.readouterr().err
    assert (out / 'thesis.tex').read_text() == 'precious'


def test_a_device_as_a_source_is_a_data_error_not_a_traceback(tmp_path, capsys):
    """C28: /dev/zero as a source ended in a NotADirectoryError traceback."""
    params = tmp_path / 'params.yaml'
    write_params_file(params, {})
    assert main(['predict', '/dev/zero', '--params', str(params), '--out',
                 str(tmp_path / 'p.csv')]) == 3
    err = capsys.readouterr().err
    assert 'neither a file nor a folder' in err and 'Traceback' not in err
    assert main(['predict', str(tmp_path / 'p.csv'), '--params', '/dev/zero', '--out',
                 str(tmp_path / 'q.csv')]) == 2
    assert 'not a regular file' in capsys.readouterr().err


def test_horizon_study_runs_under_the_interval_the_calibration_used(
        sim_table, tmp_path, monkeypatch):
    # the report's h_t x h_e study cuts its segments under the written interval, not the default
    from skidkin_ros.cli import cmd_calibrate
    table, _ = sim_table
    seen = []
    monkeypatch.setattr(cmd_calibrate, 'horizon_study',
                        lambda train, evaluate, geometry, options, *_: seen.append(options))
    assert main(['calibrate', str(table), '--out', str(tmp_path / 'p.yaml'), '--models',
                 'edd_symmetric', '--interval', 'midpoint', '--report', str(tmp_path / 'r'),
                 '--horizon-study']) == 0
    assert [o.interval for o in seen] == ['midpoint']


def test_groundtruth_takes_no_geometry_and_says_why(tmp_path, capsys):
    out = tmp_path / 'traj.csv'
    assert main(['groundtruth', str(tmp_path / 'bag'), '--out', str(out), '--wheel-radius',
                 '0.2']) == 2
    err = capsys.readouterr().err
    assert 'takes no robot geometry (--wheel-radius)' in err and 'Traceback' not in err
    assert not out.exists()
    with pytest.raises(SystemExit):
        main(['groundtruth', '--help'])
    text = capsys.readouterr().out
    assert '--jobs' in text and '--wheel-radius' not in text and '--track-width' not in text


@pytest.mark.parametrize('option, expected', [
    ('--stride', 'argument --stride: expected a whole number K >= 1 (one lidar scan in K'),
    ('--jobs', 'argument --jobs: expected a whole number of processes >= 1')])
def test_a_bad_stride_or_jobs_names_its_own_meaning(tmp_path, capsys, option, expected):
    with pytest.raises(SystemExit) as info:
        main(['groundtruth', str(tmp_path / 'bag'), '--out', str(tmp_path / 't.csv'), option,
              '0'])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert expected in err and "got '0'" in err
    assert ('processes' in err) == (option == '--jobs')


def test_estimate_lists_each_figure_once(tmp_path, capsys, monkeypatch):
    # the study itself is tested in test_consistency.py; this checks what the command prints
    from lab.cli import cmd_estimate
    from lab.cli.main import main as lab_main

    class Study:

        def summary_lines(self):
            return ['model edd_symmetric (a summary line)']

    figures = {'error_over_time': tmp_path / 'e.png', 'segment_nees': tmp_path / 'n.png'}
    monkeypatch.setattr(cmd_estimate, 'run_estimation_study', lambda **_: Study())
    monkeypatch.setattr(cmd_estimate, 'write_estimation_figures', lambda *_: figures)
    assert lab_main(['estimate', '--out', str(tmp_path / 'est'), '--quick']) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == 'model edd_symmetric (a summary line)'
    assert [line for line in lines if line.startswith('figure ')] == [
        f'figure {name}: {path}' for name, path in figures.items()]


def test_diagnose_runs_under_the_interval_of_the_parameters_file(
        sim_table, tmp_path, capsys, monkeypatch):
    # C45: the file's interval (written by calibrate) is the diagnosis's, unless one is given
    from skidkin_ros.cli import cmd_diagnose
    from skidkin_ros.errors import FitError
    table, _ = sim_table
    params = write_params_file(tmp_path / 'p.yaml', {
        'wheel_radius': 0.1651, 'track_width': 0.555, 'model': 'edd_symmetric',
        'models.edd_symmetric.alpha': 0.9, 'models.edd_symmetric.b_hat': 0.85,
        'interval': 'midpoint'}, {'source': 'test'})
    seen = []

    def spy(train, evaluate, geometry, values, base, options, **_):
        seen.append(options)
        raise FitError('stopped by the test')  # what diagnose does next is tested elsewhere

    monkeypatch.setattr(cmd_diagnose, 'diagnose', spy)
    for extra, expected in (([], 'midpoint'), (['--interval', 'starting'], 'starting')):
        assert main(['diagnose', str(table), '--params', str(params), '--out',
                     str(tmp_path / 'out.yaml'), '--no-progress', *extra]) == 4
        assert seen[-1].interval == expected
        assert seen[-1].train_segments().interval == expected
        out = capsys.readouterr().out
        assert f'sample interval: {expected}' in out
