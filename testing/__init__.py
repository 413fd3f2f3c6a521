"""Test doubles (not part of the installed packages): ``testing.fakes`` is a tiny torch-only
backend and fake methods for the harness's tests (``Cell.backend = "testing.fakes"``)."""
