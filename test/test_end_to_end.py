"""End to end through the CLI: make-bag -> run -> evaluate, and the demo."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip('rclpy')

from ar_tracking.io.bags import BagReader  # noqa: E402

CLI = [sys.executable, '-m', 'ar_tracking.cli']
REPO = Path(__file__).resolve().parents[1]


def cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    proc = subprocess.run(CLI + list(args), capture_output=True, text=True, timeout=300, cwd=cwd)
    assert 'Traceback' not in proc.stderr, proc.stderr
    return proc


@pytest.fixture(scope='module')
def sweep(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp('sweep') / 'sweep.mcap'
    proc = cli('make-bag', 'rotation_sweep', '--seed', '3', '--duration', '12', '--image-format', 'compressed',
               '-o', str(out), '-q')
    assert proc.returncode == 0, proc.stderr
    assert out.with_name('sweep.params.yaml').is_file()
    return out


@pytest.fixture(scope='module')
def kind_sweep(tmp_path_factory) -> Path:
    """The same bag from the earlier, easier simulator (its calibration is 1-3 % off; the default
    'hard' profile's rough calibration leaves a heading error of its own)."""
    out = tmp_path_factory.mktemp('sweep') / 'kind.mcap'
    proc = cli('make-bag', 'rotation_sweep', '--seed', '3', '--duration', '12', '--image-format', 'compressed',
               '--profile', 'kind', '-o', str(out), '-q')
    assert proc.returncode == 0, proc.stderr
    return out


def imu_data(path: Path) -> list[tuple[int, bytes]]:
    with BagReader(path) as bag:
        return [(m.log_time_ns, m.rawdata) for m in bag.messages(['/imu/data'])]


@pytest.fixture(scope='module')
def sweep_run(sweep, tmp_path_factory) -> tuple[Path, dict]:
    """One CLI run of the sweep (the default graph), with its JSON summary: the tests below
    score it, repeat it and compare against it."""
    out = tmp_path_factory.mktemp('sweep_run') / 'out.mcap'
    proc = cli('run', str(sweep), '-o', str(out), '-q', '--json')
    assert proc.returncode == 0, proc.stderr
    return out, json.loads(proc.stdout)


@pytest.fixture(scope='module')
def kind_runs(kind_sweep, tmp_path_factory) -> tuple[Path, Path]:
    """The kind sweep through imu_magnetometer with and without its calibration sidecar
    (/imu/data is imu_magnetometer's alone: the same bytes as in the default graph's run)."""
    d = tmp_path_factory.mktemp('kind_runs')
    cal, raw = d / 'cal.mcap', d / 'raw.mcap'
    assert cli('run', str(kind_sweep), '-o', str(cal), '-q', '--nodes', 'imu_magnetometer').returncode == 0
    assert cli('run', str(kind_sweep), '-o', str(raw), '-q', '--nodes', 'imu_magnetometer',
               '--no-sidecar').returncode == 0
    return cal, raw


def test_run_and_evaluate_rotation_sweep(sweep_run):
    out, summary = sweep_run
    assert {'imu_magnetometer', 'panorama_mapper'} <= set(summary['nodes']) and summary['output_messages'] > 1000
    proc = cli('evaluate', str(out), '--json')
    assert proc.returncode == 0, proc.stderr
    metrics = json.loads(proc.stdout)
    m = metrics['orientation']['imu/data']
    for key in ('rmse_deg', 'heading_rmse_deg', 'tilt_rmse_deg', 'max_deg', 'n'):
        assert key in m
    assert m['n'] >= 1100
    # The sensor-only heading follows the simulated disturbances of 2-10 deg: clearly wrong
    # during them, sane outside: neither zero nor wild.
    assert 0.5 < m['heading_rmse_deg'] < 8.0
    assert 3.0 < m['max_deg'] < 20.0
    assert m['tilt_rmse_deg'] < 1.5
    # VQF on the same IMU samples is the reference row; imu_magnetometer is VQF on stamps.
    ref = metrics['orientation']['reference/vqf']
    assert ref['n'] >= 1100 and abs(ref['heading_rmse_deg'] - m['heading_rmse_deg']) < 0.5
    assert metrics['orientation']['orientation/global']['n'] > 300
    assert metrics['bag']['world_alignment'] == 'none'


def test_two_runs_give_identical_estimates(sweep, sweep_run, tmp_path):
    """/imu/data again, from imu_magnetometer alone (its topic: the same bytes as in the default
    graph's run, which takes twice as long; test_estimates_do_not_depend_on_the_ground_truth runs
    the whole graph a second time and compares every estimate)."""
    first, _ = sweep_run
    again = tmp_path / 'again.mcap'
    assert cli('run', str(sweep), '-o', str(again), '-q', '--nodes', 'imu_magnetometer').returncode == 0
    assert imu_data(again) == imu_data(first) and len(imu_data(again)) > 1000


def test_calibration_sidecar_matters(kind_runs):
    """Without the device calibration, hard/soft iron distort the heading (a real effect)."""
    cal, raw = kind_runs
    h_cal = json.loads(cli('evaluate', str(cal), '--json').stdout)['orientation']['imu/data']['heading_rmse_deg']
    h_raw = json.loads(cli('evaluate', str(raw), '--json').stdout)['orientation']['imu/data']['heading_rmse_deg']
    assert h_raw > 1.5 * h_cal


def test_evaluate_report_html(kind_runs, tmp_path):
    """evaluate without --json: the console summary and an HTML report with its figure (the
    default graph's report - panorama sections too - is the demo's, test_demo_on_the_sample_bag)."""
    out, _ = kind_runs
    proc = cli('evaluate', str(out), '--report', str(tmp_path / 'r.html'))
    assert proc.returncode == 0 and 'imu/data' in proc.stdout
    html = (tmp_path / 'r.html').read_text()
    assert 'imu/data' in html and 'data:image/png;base64' in html


def test_evaluate_needs_ground_truth(tmp_path):
    from bagfactory import write_turning_imu_bag
    from ar_tracking.io.bags import BagWriter

    src = write_turning_imu_bag(tmp_path / 'in.mcap', seconds=0.2)
    stripped = tmp_path / 'nogt.mcap'
    with BagReader(src) as r, BagWriter(stripped) as w:
        for m in r.messages(['/imu/data_raw']):
            w.write(m.topic, m.log_time_ns, m.rawdata, msgtype=m.msgtype)
    proc = cli('evaluate', str(stripped), '--json')
    assert proc.returncode == 1 and 'ground_truth' in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


def test_make_bag_unknown_scenario_is_one_line(tmp_path):
    proc = cli('make-bag', 'moon_landing', '-o', str(tmp_path / 'x.mcap'))
    assert proc.returncode == 1 and 'moon_landing' in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


@pytest.fixture(scope='module')
def demo(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    """One ``ar-tracking demo -q`` (the orientation graph on the sample bag, evaluate, report):
    its workdir and process, for the demo test and the sample bag's seam measures."""
    if not (REPO / 'bags' / 'rotation_sweep_authoring.mcap').is_file():
        pytest.fail('the sample bag bags/rotation_sweep_authoring.mcap is missing from the repository')
    workdir = tmp_path_factory.mktemp('demo')
    return workdir, cli('demo', '--workdir', str(workdir), '-q')


def test_demo_on_the_sample_bag(demo):
    tmp_path, proc = demo
    assert proc.returncode == 0, proc.stderr
    # exactly the nodes the README names (no SLAM on this rotate-in-place bag)
    assert 'nodes: imu_magnetometer, panorama_mapper, hybrid_orientation_filter\n' in proc.stderr
    assert 'imu/data: orientation rmse' in proc.stdout
    assert (tmp_path / 'report.html').stat().st_size > 10_000
    assert (tmp_path / 'report.png').stat().st_size > 10_000
    metrics = json.loads((tmp_path / 'metrics.json').read_text())
    assert metrics['orientation']['imu/data']['n'] > 1000


def test_seam_errors_on_the_sample_bag_prefer_edr(demo):
    """The seam measures of the sample bag (panorama_metrics.seam_errors, all 600 frames), as
    the demo's evaluate scored them from the run's source bag (it replays the mapper core
    with each map variant; a second replay here would only repeat it)."""
    tmp_path, proc = demo
    assert proc.returncode == 0, proc.stderr
    s = json.loads((tmp_path / 'metrics.json').read_text())['panorama']['seam_error']
    assert s['edr_revisit'] < 0.5 * s['8bit_revisit']
    for name in ('edr', '8bit', 'edr_paper'):  # the step, its mean |step| and the naive figure
        assert {name, f'mean_abs_{name}', f'pixelwise_{name}', f'{name}_revisit'} <= s.keys()
    assert s['ratio'] == pytest.approx(s['edr'] / s['8bit'], abs=1e-3)
    assert s['edr'] < s['edr_paper']  # smoothed offsets add fewer steps than per-frame ones
    assert s['pixelwise_8bit'] > 5 * s['8bit']  # texture dominates the naive figure


def test_estimates_do_not_depend_on_the_ground_truth_nor_on_the_process_layout(sweep, sweep_run, tmp_path):
    """The truth is for evaluate and the benches only: the same bag without any /ground_truth/*
    topic (and the same calibration sidecar) gives byte-identical outputs - here run with every
    node in a process of its own (``--executor processes``, the runner carrying the messages),
    against the one-process run of the sweep: the same bag but for the truth, message for
    message and byte for byte."""
    from ar_tracking.io.bags import BagWriter

    blind = tmp_path / 'blind.mcap'
    with BagReader(sweep) as r, BagWriter(blind) as w:
        kept = [t for t in r.topics if not t.startswith('/ground_truth/')]
        assert len(kept) < len(r.topics)
        for m in r.messages(kept):
            w.write(m.topic, m.log_time_ns, m.rawdata, msgtype=m.msgtype)
    blind.with_name('blind.params.yaml').write_text(sweep.with_name('sweep.params.yaml').read_text())
    a, summary = sweep_run
    b = tmp_path / 'b.mcap'
    proc = cli('run', str(blind), '-o', str(b), '-q', '--json', '--executor', 'processes')
    assert proc.returncode == 0, proc.stderr
    assert summary['executor'] == 'events' and json.loads(proc.stdout)['executor'] == 'processes'
    outputs = ['/imu/data', '/panorama/orientation', '/orientation/global', '/orientation/panorama_in_world']

    def messages(path: Path) -> list[tuple[str, int, bytes]]:
        with BagReader(path) as bag:
            return [(m.topic, m.log_time_ns, bytes(m.rawdata)) for m in bag.messages()
                    if not m.topic.startswith('/ground_truth/')]

    got, want = messages(b), messages(a)
    assert all(sum(t == topic for t, _, _ in want) > 100 for topic in outputs)
    assert '/panorama/image' in {t for t, _, _ in want}
    assert got == want
