"""Outputs are what their names say: ``simulate -o X.mcap`` writes the one MCAP file X.mcap."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from flexforce.cli import main
from flexforce.datasets.io.bagio import load_recording
from flexforce.datasets.io.export import mcap_file_output
from flexforce.errors import BagError


def test_simulate_into_an_mcap_name_writes_one_mcap_file(tmp_path, capsys):
    out = tmp_path / "walk.mcap"
    assert main(["simulate", "stand", "--duration", "0.2", "-o", str(out), "-q"]) == 0
    assert f"wrote {out}:" in capsys.readouterr().out
    assert out.is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["walk.mcap"]  # no folder, temporary or lock
    rec = load_recording(out)
    assert rec.n == 41 and rec.truth is not None and rec.meta["scenario"]["name"] == "stand"


def test_simulate_into_an_mcap_name_refuses_then_replaces(tmp_path, capsys):
    out = tmp_path / "r.mcap"
    assert main(["simulate", "stand", "--duration", "0.1", "-o", str(out), "-q"]) == 0
    first = out.read_bytes()
    assert main(["simulate", "stand", "--duration", "0.2", "-o", str(out), "-q"]) == 1
    assert "exists already" in capsys.readouterr().err and out.read_bytes() == first
    assert main(["simulate", "stand", "--duration", "0.2", "-o", str(out), "--force", "-q"]) == 0
    assert load_recording(out).n == 41
    folder = tmp_path / "d.mcap"
    folder.mkdir()
    (folder / "keep.txt").write_text("x")
    assert main(["simulate", "stand", "--duration", "0.1", "-o", str(folder), "--force", "-q"]) == 1
    assert "not an MCAP file" in capsys.readouterr().err and (folder / "keep.txt").exists()


def test_an_interrupted_mcap_file_output_leaves_the_previous_file(tmp_path):
    out = tmp_path / "x.mcap"
    out.write_bytes(b"previous")
    with pytest.raises(KeyboardInterrupt), mcap_file_output(out, overwrite=True) as bag:
        bag.mkdir()
        (bag / "x_0.mcap").write_bytes(b"new")
        raise KeyboardInterrupt
    assert out.read_bytes() == b"previous"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.mcap"]


def test_mcap_file_output_takes_exactly_one_mcap_file(tmp_path):
    with pytest.raises(BagError, match="holds 0 MCAP files; expected exactly one"), \
            mcap_file_output(tmp_path / "y.mcap") as bag:
        bag.mkdir()
    assert not (tmp_path / "y.mcap").exists()
    with mcap_file_output(tmp_path / "z.mcap") as bag:
        bag.mkdir()
        (bag / "z_0.mcap").write_bytes(np.arange(3, dtype=np.uint8).tobytes())
    assert (tmp_path / "z.mcap").read_bytes() == b"\x00\x01\x02"


# ---- where the compiled kernels are cached (flexforce.jit) -------------------------------------------

TINY = "from flexforce.jit import njit\n\n\n@njit\ndef add(a, b):\n    return a + b\n"


def _tiny_kernel(folder, name="tiny_kernel"):
    """A module holding one njit kernel, imported from ``folder`` (a fresh dispatcher each call)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, folder / "tiny_kernel.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.add


@pytest.fixture
def kernel_source(tmp_path, monkeypatch):
    """A read-only source folder with the tiny kernel, a user cache under tmp_path, numba's own
    cache setting cleared, the compile notice on and not yet written."""
    numba = pytest.importorskip("numba")
    from flexforce import jit

    src = tmp_path / "src"
    src.mkdir()
    (src / "tiny_kernel.py").write_text(TINY)
    src.chmod(0o555)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    monkeypatch.setattr(numba.config, "CACHE_DIR", "")
    monkeypatch.setattr(jit, "_announced", False)
    monkeypatch.setattr(jit, "_notice_mode", True)
    yield src
    src.chmod(0o755)


def _cached(folder):
    return sorted(p.name for p in folder.rglob("*") if p.suffix in (".nbi", ".nbc"))


def test_kernels_are_cached_in_the_user_cache_not_the_source_tree(kernel_source, tmp_path, capsys):
    from flexforce import jit

    assert jit.kernel_cache_dir() == tmp_path / "xdg" / "flexforce" / "numba"
    add = _tiny_kernel(kernel_source)
    assert add(2, 3) == 5
    err = capsys.readouterr().err
    assert err.startswith("flexforce: compiling the numerical kernels (first run") and err.count("\n") == 1
    assert str(tmp_path / "xdg" / "flexforce" / "numba") in err
    assert add.stats.cache_misses and not add.stats.cache_hits
    assert any(name.startswith("tiny_kernel.add-") for name in _cached(tmp_path / "xdg" / "flexforce" / "numba"))
    assert _cached(kernel_source) == []  # nothing beside the sources
    # a second process (a fresh dispatcher, the notice not yet written) loads it, silently
    jit._announced = False
    again = _tiny_kernel(kernel_source, "tiny_kernel_again")
    assert again(1.5, 2.0) == 3.5 and again(4, 5) == 9
    assert again.stats.cache_hits and capsys.readouterr().err.count("compiling") == 1  # float64: compiled once


def test_an_unwritable_user_cache_falls_back_to_the_source_tree(kernel_source, tmp_path, monkeypatch, capsys):
    (tmp_path / "afile").write_text("x")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "afile"))  # a file: no cache folder can be made there
    kernel_source.chmod(0o755)
    add = _tiny_kernel(kernel_source)
    assert add(2, 3) == 5 and add.stats.cache_misses
    assert any(name.startswith("tiny_kernel.add-") for name in _cached(kernel_source / "__pycache__"))


def test_the_compile_notice_follows_its_setting(kernel_source, monkeypatch, capsys):
    from flexforce import jit

    jit.set_compile_notice(False)
    assert _tiny_kernel(kernel_source)(1, 1) == 2
    assert capsys.readouterr().err == ""
    jit.set_compile_notice(None)  # stderr captured by pytest: no terminal, no notice
    assert _tiny_kernel(kernel_source, "tiny_b")(1.0, 1.0) == 2.0
    assert capsys.readouterr().err == ""


def test_a_kernel_called_with_constants_is_compiled_once_per_type(kernel_source, tmp_path):
    """A kernel called from a kernel with literal arguments (offsets, flags) is compiled for their
    types, not once per value; each signature's cache entry has a data file of its own."""
    (tmp_path / "lit").mkdir()
    (tmp_path / "lit" / "tiny_kernel.py").write_text(
        "from flexforce.jit import njit\n\n\n@njit\ndef at(a, o):\n    return a[o] + a[o + 1]\n\n\n"
        "@njit\ndef add(a, b):\n    return at(a, 0) + at(a, 2) + at(a, 4) + b\n")
    add = _tiny_kernel(tmp_path / "lit")
    assert add(np.arange(6.0), 1.0) == 16.0 and add(np.arange(6.0), 1) == 16.0
    at = add.py_func.__globals__["at"]
    assert len(at.signatures) == 1, at.signatures  # (array, int64): not one per literal offset
    assert len(add.signatures) == 2
    data = [name for name in _cached(tmp_path / "xdg") if name.startswith("tiny_kernel.add-")
            and name.endswith(".nbc")]
    assert len(data) == 2 and not any(name.split(".")[-2].isdigit() for name in data)  # keyed, not numbered


def test_kernels_compiled_by_a_helper_process_are_awaited_and_loaded(kernel_source, monkeypatch, capsys):
    """compile_elsewhere: the helper compiles and caches the listed kernels from the end of the
    listing (a stale entry skipped); this process, needing one the helper has taken, waits and
    loads it from the cache instead of compiling it too; one nobody has taken it compiles itself."""
    import time

    from flexforce import jit

    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(kernel_source), os.environ.get("PYTHONPATH", "")]))
    monkeypatch.syspath_prepend(str(kernel_source))  # the module named in the listing, here as in the helper
    add = _tiny_kernel(kernel_source)
    assert not jit.cached(add)
    listing = [("tiny_kernel", "add", "(int64, int64)"), ("tiny_kernel", "add", "(float64, float64)"),
               ("tiny_kernel", "gone", "(int64,)")]
    jit.compile_elsewhere(listing)
    assert "compiling the numerical kernels" in capsys.readouterr().err
    work = jit._work[0]
    for _ in range(600):  # the helper takes the last entries first: the stale one, then float64's
        if os.path.exists(os.path.join(work, "1.taken")):
            break
        time.sleep(0.05)
    assert add(0.5, 1.0) == 1.5
    assert add.stats.cache_hits and not add.stats.cache_misses  # awaited, loaded
    assert add(2, 3) == 5  # compiled here or by the helper, whichever took it first
    assert jit.cached(add)
    for proc in jit._helpers:
        assert proc.wait(timeout=60) == 0
    assert sorted(os.listdir(work)) == ["0.taken", "1.taken", "2.taken", "kernels.json"]
    jit._stop_helpers()
    assert not jit._work and not jit._listed and not os.path.exists(work)


def test_the_demo_starts_no_helper_on_one_core(tmp_path, monkeypatch, capsys):
    """A first demo (an empty cache) with one usable core: no helper, the compile notice at once."""
    from flexforce import jit, pipeline
    from flexforce.compare import runner

    monkeypatch.setattr(runner, "usable_cores", lambda: 1)
    monkeypatch.setattr(jit, "cached", lambda *kernels: False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setattr(jit, "_announced", False)
    monkeypatch.setattr(jit, "_notice_mode", True)
    pipeline.prepare_demo_kernels()
    assert not jit._helpers and str(tmp_path) in capsys.readouterr().err


def test_recorded_signatures_read_back():
    """The demo's listing: each kernel exists, each signature reads back as the numba types it names."""
    import importlib

    pytest.importorskip("numba")
    from flexforce.demo_kernels import DEMO_KERNELS
    from flexforce.jit import _signature

    assert DEMO_KERNELS
    for module, function, signature in DEMO_KERNELS:
        assert hasattr(importlib.import_module(module), function), (module, function)
        assert repr(_signature(signature)) == signature


def test_relative_xdg_cache_home_is_ignored(monkeypatch):
    from flexforce.jit import kernel_cache_dir

    monkeypatch.setenv("XDG_CACHE_HOME", "relative/cache")
    assert kernel_cache_dir() == Path.home() / ".cache" / "flexforce" / "numba"
    monkeypatch.delenv("XDG_CACHE_HOME")
    assert kernel_cache_dir() == Path.home() / ".cache" / "flexforce" / "numba"


# ---- the demo report in a real browser --------------------------------------------------------------

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


def _browser() -> str | None:
    import shutil

    return next((path for name in BROWSERS if (path := shutil.which(name))), None)


def screenshot(browser: str, page: Path, png: Path, size=(1280, 4000)) -> None:
    """A headless browser's screenshot of ``page`` (the top ``size`` pixels)."""
    import subprocess

    subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                    f"--window-size={size[0]},{size[1]}", f"--screenshot={png}", page.resolve().as_uri()],
                   capture_output=True, timeout=120, check=True)


@pytest.mark.slow
def test_the_demo_report_renders_in_a_browser(tmp_path):
    """``flexforce demo`` writes a report that a headless Chromium draws: text, tables and figures
    (not a blank page), the verdict sentence first, every figure loaded."""
    import re
    import subprocess
    import sys

    from PIL import Image

    browser = _browser()
    if browser is None:
        pytest.skip(f"no headless browser: none of {', '.join(BROWSERS)} is on PATH (e.g. apt-get install chromium)")
    out = tmp_path / "demo"
    proc = subprocess.run([sys.executable, "-m", "flexforce.cli", "demo", "-o", str(out), "-q"], capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    html = (out / "index.html").read_text(encoding="utf-8")
    verdict = re.search(r"[A-Z][\w -]*: \w+ is best \([\d.]+ [^)]*\)", html)
    assert verdict, "the report states no verdict (which estimator is best, by how much)"
    assert html.index(verdict[0]) < html.index("<h2"), "the verdict comes before the first section"
    for src in re.findall(r'<img[^>]+src="([^"]+)"', html):
        assert src.startswith("data:") or (out / src).is_file(), f"figure {src} is missing"
    png = tmp_path / "report.png"
    screenshot(browser, out / "index.html", png)
    pixels = np.asarray(Image.open(png).convert("L"), dtype=float)
    assert pixels.shape == (4000, 1280)
    inked = (pixels < 200).mean()
    assert 0.01 < inked < 0.6, f"{100 * inked:.2f} % of the screenshot is drawn: a blank or broken page"
    assert pixels[:300].std() > 20, "no text at the top of the page"


def _rendered(browser: str, page: Path, png: Path) -> np.ndarray:
    """The page's screenshot as grey levels, checked to be drawn (not blank, text at the top)."""
    from PIL import Image

    screenshot(browser, page, png)
    pixels = np.asarray(Image.open(png).convert("L"), dtype=float)
    inked = (pixels < 200).mean()
    assert 0.01 < inked < 0.6, f"{100 * inked:.2f} % of the screenshot of {page} is drawn: a blank or broken page"
    assert pixels[:300].std() > 20, f"no text at the top of {page}"
    return pixels


def _figures_load(html: str, out: Path) -> list[str]:
    import re

    srcs = re.findall(r'<img[^>]+src="([^"]+)"', html)
    for src in srcs:
        assert src.startswith("data:") or (out / src).is_file(), f"figure {src} is missing"
    return srcs


@pytest.mark.slow
def test_the_comparison_report_of_a_real_walk_renders_in_a_browser(tmp_path):
    """``flexforce compare`` of the iCub walk: the verdict per quantity before the first section,
    every figure there, the F/T and Vicon references named on the plots that have them, the model
    band's row in the force bands, drawn by a headless Chromium."""
    import html as html_lib
    import re
    import subprocess
    import sys

    from conftest import ICUB_DIR

    browser = _browser()
    if browser is None:
        pytest.skip(f"no headless browser: none of {', '.join(BROWSERS)} is on PATH (e.g. apt-get install chromium)")
    walk = ICUB_DIR / "icub-walk-12s"
    if not walk.exists():
        pytest.skip(f"the iCub recordings are not beside the checkout ({ICUB_DIR})")
    out = tmp_path / "walk"
    proc = subprocess.run([sys.executable, "-m", "flexforce.cli", "compare", str(walk), "--robot", "icub-identified",
                           "-o", str(out), "-q"], capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    page = (out / "index.html").read_text(encoding="utf-8")
    text = html_lib.unescape(page)
    first = text.index("<h2")
    for quantity in ("Per-foot vertical force", "Total vertical force", "Tilt"):
        found = re.search(quantity + r": [^<]*best \([\d.]+ (N|mrad)\)", text)
        assert found and found.start() < first, f"no verdict on {quantity} before the first section"
    assert "<title>" in page and "icub-walk-12s" in text[:first], "the title does not name the recording"
    srcs = _figures_load(page, out)
    assert {"forces.png", "foot_forces.png", "flexibility.png", "errors.png"} <= set(srcs), srcs
    assert "(model band)" in text and "With the model's own uncertainty" in text
    _rendered(browser, out / "index.html", tmp_path / "walk.png")


@pytest.mark.slow
def test_the_diagnosis_report_renders_in_a_browser(tmp_path):
    """``flexforce diagnose --add auto`` of a simulated push: the verdict box first, naming the
    effect found, its fitted value with units after the addition, drawn by a headless Chromium."""
    import html as html_lib
    import subprocess
    import sys

    browser = _browser()
    if browser is None:
        pytest.skip(f"no headless browser: none of {', '.join(BROWSERS)} is on PATH (e.g. apt-get install chromium)")
    out = tmp_path / "diag"
    proc = subprocess.run([sys.executable, "-m", "flexforce.cli", "diagnose", "push-pitch", "--end", "3",
                           "--add", "auto", "-o", str(out), "-q"], capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    page = (out / "index.html").read_text(encoding="utf-8")
    text = html_lib.unescape(page)
    verdict = text.index('id="verdict"')
    assert verdict < text.index("<h2"), "the verdict does not come first"
    box = text[verdict:text.index("</div>", verdict)]
    assert "external" in box.lower() or "push" in box.lower(), box
    assert 'id="added-values"' in text and " N" in text[text.index('id="added-values"'):][:2000]
    _figures_load(page, out)
    _rendered(browser, out / "index.html", tmp_path / "diag.png")


def test_the_browser_test_skips_with_a_reason_without_a_browser(monkeypatch):
    import shutil

    monkeypatch.setattr(shutil, "which", lambda name: None)
    assert _browser() is None


def test_the_demo_runs_the_general_window_path_until_the_compiled_one_is_cached(monkeypatch):
    """``demo_options``: the fixed-lag smoother's general window path (the same estimates,
    ``tests/test_window_update.py``) while the cache lacks the compiled window update, none after."""
    from flexforce import jit, pipeline
    from flexforce.smoother import window_kernel

    asked = []

    def cached(*kernels):
        asked.extend(kernels)
        return state["cached"]

    state = {"cached": False}
    monkeypatch.setattr(jit, "cached", cached)
    assert pipeline.demo_options() == {"fixed-lag": {"compiled": False}}
    assert asked == [window_kernel.window_update]
    state["cached"] = True
    assert pipeline.demo_options() == {}


def test_kernels_compiled_while_awaiting_a_helper_are_compiled_here_not_awaited(kernel_source, tmp_path, monkeypatch):
    """compile_while_awaiting: while a helper compiles what this process needs next, this process
    compiles the listed kernels nobody has taken, from the front (a stale entry skipped, one the
    helper took left to it), and never waits for a kernel it took itself."""
    import sys

    from flexforce import jit

    monkeypatch.syspath_prepend(str(kernel_source))
    monkeypatch.delitem(sys.modules, "tiny_kernel", raising=False)
    work = str(tmp_path / "work")
    os.mkdir(work)
    listing = {("tiny_kernel", "add", "(int64, int64)"): (work, 0),
               ("tiny_kernel", "add", "(float64, float64)"): (work, 1),
               ("tiny_kernel", "gone", "(int64,)"): (work, 2)}
    monkeypatch.setattr(jit, "_listed", listing)
    monkeypatch.setattr(jit, "_mine", set())
    monkeypatch.setattr(jit, "_helpers_running", lambda: True)  # a helper still compiling the awaited kernel
    monkeypatch.setattr(jit, "cached", lambda *kernels: False)
    assert jit._take(work, 1)  # the helper's
    assert jit.compile_while_awaiting() == 1  # (int64, int64) here; the float64 one left to the helper
    assert sorted(os.listdir(work)) == ["0.taken", "1.taken", "2.taken"]
    add = sys.modules["tiny_kernel"].add
    assert [tuple(map(str, s)) for s in add.signatures] == [("int64", "int64")]
    from numba import float64, int64

    assert not jit._taken_elsewhere(add.py_func, (int64, int64))  # its own: compiled here, not awaited
    assert jit._taken_elsewhere(add.py_func, (float64, float64))  # the helper's: awaited
