"""A newcomer's mistakes with the ``skidkin`` command get one line that says what to do."""

import pytest
from skidkin_ros.adapters.sim_writer import write_truth_csv
from skidkin_ros.cli.main import main
from skidkin_ros.sim.simulate import SimConfig, simulate


@pytest.fixture(scope='module')
def table_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp('husky_like')
    table = write_truth_csv(simulate(SimConfig(duration_s=20.0, seed=3)), folder / 'drive.csv')
    (folder / 'README.md').write_text('what the table holds\n')
    (folder / 'LICENSE.txt').write_text('licence\n')
    return folder, table


def test_c221_split_by_beside_eval_is_refused_not_ignored(table_folder, tmp_path, capsys):
    _, table = table_folder
    for command in (['calibrate', str(table), '--eval', str(table), '--split-by', 'segment',
                     '--out', str(tmp_path / 'p.yaml')],
                    ['diagnose', str(table), '--eval', str(table), '--split-by', 'segment',
                     '--params', str(tmp_path / 'any.yaml'), '--out', str(tmp_path / 'a.yaml')]):
        assert main(command) == 2
        err = capsys.readouterr().err
        assert err.count('\n') == 1 and 'Traceback' not in err
        assert '--split-by segment splits TRAIN' in err and 'drop --split-by' in err
    assert list(tmp_path.iterdir()) == []


def test_c222_a_folder_of_tables_names_the_table_to_pass(table_folder, tmp_path, capsys):
    folder, table = table_folder
    out = tmp_path / 'p.yaml'
    assert main(['calibrate', str(folder), '--out', str(out)]) == 3
    err = capsys.readouterr().err
    assert 'Traceback' not in err and not out.exists()
    assert f'{folder} is a folder of trajectory tables, not a recording' in err
    assert f'pass the table file itself ({table})' in err
    assert 'LICENSE.txt' not in err.split('itself')[1]
    # The folder of a recording is still read as one: a bag beside a table is not refused here.
    (folder / 'drive.mcap').write_bytes(b'')
    try:
        assert main(['calibrate', str(folder), '--out', str(out)]) == 3
        assert 'folder of trajectory tables' not in capsys.readouterr().err
    finally:
        (folder / 'drive.mcap').unlink()


def test_c223_a_folder_of_recordings_and_tables_names_both(tmp_path, capsys):
    """`skidkin simulate --out runs/a` writes runs/a/ beside runs/a_truth.csv: name them both."""
    runs = tmp_path / 'runs'
    runs.mkdir()
    assert main(['simulate', '--out', str(runs / 'a'), '--duration', '4']) == 0
    assert (runs / 'a_truth.csv').is_file()
    capsys.readouterr()
    out = tmp_path / 'p.yaml'
    assert main(['calibrate', str(runs), '--ground-truth', 'none', '--out', str(out)]) == 3
    err = capsys.readouterr().err
    assert 'Traceback' not in err and not out.exists()
    assert f'{runs} is not a recording: it holds recording folder(s) ({runs / "a"})' in err
    assert f'trajectory table(s) ({runs / "a_truth.csv"}); pass one of them' in err
