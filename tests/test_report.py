"""``pidg report``: one self-contained page with a suite's tables, the runs' curves and their pictures."""
import pidg  # noqa: F401  (sets OMP_WAIT_POLICY before torch is imported)

import base64
import dataclasses
import io
import re

import pytest
from PIL import Image

from pidg.bench.suite import run_suite
from pidg.data.procedural import write_procedural_dataset
from pidg.report import build_report

from bench.test_suite import TINY, tiny_train_config  # the suite tests' tiny scene and schedule


def test_a_report_holds_the_tables_the_curves_and_the_pictures(tmp_path):
    write_procedural_dataset(TINY, tmp_path / "scenes" / "alpha")
    config = tiny_train_config(iterations=6)
    config.output = dataclasses.replace(config.output, log_every=1)
    suite = tmp_path / "suite"
    run_suite("pidg", tmp_path / "scenes", suite, config, minutes=None, variants=["base", "cmr"], log=lambda s: None)
    page = build_report([suite, suite / "alpha" / "base"], tmp_path / "report" / "r.html").read_text()
    assert page.count("<h3>alpha: ") == 2  # the run named twice appears once
    assert "zero-padded" in page and "<b>" in page and "PIDG w/o LPFM" in page
    assert page.count("<polyline") == 2  # one PSNR curve per variant
    images = re.findall(r"data:image/png;base64,([A-Za-z0-9+/=]+)", page)
    captions = re.findall(r"<figcaption>([^<]*)</figcaption>", page)
    assert any(c.startswith("velocity, px") for c in captions) and any("stress" in c for c in captions)
    assert any("motion | Gaussian | velocity flow" in c for c in captions)
    assert len(images) == len(captions) >= 5
    first = Image.open(io.BytesIO(base64.b64decode(images[0])))
    assert first.size == (2 * TINY.width, TINY.height)  # render | ground truth
    assert len(list((tmp_path / "report" / "r_pictures").glob("*.png"))) == len(images)


def test_bad_inputs_are_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="nowhere: no such file"):
        build_report([tmp_path / "nowhere"], tmp_path / "r.html")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="empty: not a run folder"):
        build_report([tmp_path / "empty"], tmp_path / "r.html")
