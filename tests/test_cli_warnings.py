"""A warning during a command is one log line a user can read, not Python's file:line form with pidg's source."""
import logging
import warnings

from pidg.cli import warnings_as_log_lines


def test_a_warning_becomes_one_log_line_and_python_s_form_returns_after(caplog):
    format_before, show_before = warnings.formatwarning, warnings.showwarning
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        with caplog.at_level(logging.WARNING), warnings_as_log_lines():
            warnings.warn("ms_ssim reported as None: the image is too small", RuntimeWarning)
        assert warnings.formatwarning is format_before and warnings.showwarning is show_before
    lines = [r.getMessage() for r in caplog.records if r.name == "py.warnings"]
    assert lines == ["RuntimeWarning: ms_ssim reported as None: the image is too small"]
