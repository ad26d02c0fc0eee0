"""The README's Quick tour and Python example, run verbatim after the demo (as a new user would)."""
import os
import re
import shutil
import subprocess
import sys
from tests.workflow_helpers import ROOT



def _block(lang, after):
    text = open(os.path.join(ROOT, "README.md")).read()
    text = text[text.index(after):]
    return re.search(rf"```{lang}\n(.*?)```", text, re.S).group(1)


def test_quick_tour_and_python_example_run_verbatim_after_the_demo(tmp_path):
    shutil.copytree(os.path.join(ROOT, "workflows"), tmp_path / "workflows")
    venv_bin = tmp_path / ".venv" / "bin"  # stands for the .venv that `make demo` creates
    venv_bin.mkdir(parents=True)
    (venv_bin / "activate").write_text(f'export PATH="{os.path.dirname(sys.executable)}:$PATH"\n')
    env = dict(os.environ, PYTHONPATH=ROOT)
    demo = subprocess.run([sys.executable, "-m", "mmflow.cli", "run", "workflows/demo.yaml"],  # as `make demo`
                          cwd=tmp_path, env=env, capture_output=True, text=True)
    assert demo.returncode == 0, demo.stderr[-3000:]
    assert "\r" not in demo.stdout and "[transfer] " in demo.stdout  # progress lines, no bar, off a terminal
    assert "[transfer] done" in (tmp_path / "runs" / "demo" / "mmflow.log").read_text()
    assert f"{tmp_path}/runs/demo/maps/map_40.000MHz.fits" in demo.stdout  # absolute paths at the end
    assert "resolution ~" in demo.stdout and "singular values above sqrt(eps)" in demo.stdout

    lines = [ln for ln in _block("bash", "## Quick tour").splitlines() if ln.strip()]
    script = "\n".join(f"{ln}\necho \"RC=$? :: {i}\"" for i, ln in enumerate(lines))
    out = subprocess.run(["bash", "-c", script], cwd=tmp_path, env=env, capture_output=True, text=True)
    log = out.stdout + out.stderr
    codes = {int(i): int(rc) for rc, i in re.findall(r"RC=(\d+) :: (\d+)", out.stdout)}
    assert len(codes) == len(lines), log[-3000:]
    for i, ln in enumerate(lines):
        expected = 2 if "refused (exit 2)" in ln else 0
        assert codes[i] == expected, f"{ln!r} exited {codes[i]}:\n{log[-3000:]}"
    assert "imaging.eps: 0.01 -> 0.001" in log and "--force" in log  # the refusal names the change and fixes
    assert "STALE" in log and "products" in log  # the single-stage run says what is now stale
    assert "maps below are STALE" in log  # ... and does not show the old maps as current
    assert (tmp_path / "my-workflow.yaml").exists()
    assert "largest task: transfer" in log and "GB live at the peak" in log  # the plan of the paper's channel

    code = _block("python", "The same engine in Python")
    py = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert py.returncode == 0, py.stderr[-3000:]
    assert (tmp_path / "my_map_40MHz.png").stat().st_size > 10_000 and "rms" in py.stdout
