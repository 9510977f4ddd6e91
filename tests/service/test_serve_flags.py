"""`ds3d-serve` flags: one per Settings field, with its description, default and env var in
--help; flags over env vars over defaults; bad values exit 2 naming the setting. Parsing only,
no server start."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from pydantic import SecretStr

from ds3d_service.__main__ import main, parse_settings
from ds3d_service.settings import Settings

FIELDS = Settings.model_fields


def flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def env_var(name: str) -> str:
    return "DS3D_" + name.upper()


@pytest.fixture(autouse=True)
def clean_env(monkeypatch):
    """No DS3D_* setting from the caller's environment; a wide terminal for --help."""
    for name in FIELDS:
        monkeypatch.delenv(env_var(name), raising=False)
    monkeypatch.setenv("COLUMNS", "400")


def test_every_setting_has_a_description():
    assert [name for name, field in FIELDS.items() if not field.description] == []


def test_help_lists_every_setting(capsys):
    with pytest.raises(SystemExit) as exc:
        parse_settings(["--help"])
    assert exc.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    for name, field in FIELDS.items():
        factory = field.default_factory
        default = (
            f"(default factory: {getattr(factory, '__name__', '')})"
            if factory is not None
            else f"(default: {'null' if field.default is None else field.default})"
        )
        description = " ".join(field.description.split())
        assert f"{flag(name)} " in text, name
        assert f"{description} {default} [env: {env_var(name)}]" in text, name


def test_defaults_without_flags_or_env():
    assert parse_settings([]) == Settings()
    assert parse_settings([]).port == 8000


def test_env_var_overrides_default(monkeypatch):
    monkeypatch.setenv("DS3D_MAX_BATCH_SIZE", "8")
    assert parse_settings([]).max_batch_size == 8


def test_flag_overrides_env_var(monkeypatch):
    monkeypatch.setenv("DS3D_MAX_BATCH_SIZE", "8")
    monkeypatch.setenv("DS3D_PORT", "9000")
    s = parse_settings(["--max-batch-size", "32", "--port=9001"])
    assert (s.max_batch_size, s.port) == (32, 9001)


def test_every_field_is_a_flag():
    values = {
        "host": ("0.0.0.0", "0.0.0.0"),
        "model_dir": ("/tmp/models", Path("/tmp/models")),
        "device": ("cuda", "cuda"),
        "log_level": ("debug", "debug"),
        "max_wait_ms": ("2.5", 2.5),
        "request_timeout_s": ("3.5", 3.5),
        "keep_alive_s": ("2.5", 2.5),
        "max_header_bytes": ("32768", 32768),
        "allocator": ("system", "system"),
        "api_keys": ("a-key-of-sixteen-or-more", SecretStr("a-key-of-sixteen-or-more")),
        "require_api_keys": ("true", True),
        "metrics_public": ("true", True),
        "caller_queue_share": ("0.25", 0.25),
        "cors_origins": ("https://app.example.org", "https://app.example.org"),
    }
    argv, want = [], {}
    for name in FIELDS:
        text, value = values.get(name, ("7", 7))
        argv += [flag(name), text]
        want[name] = value
    assert parse_settings(argv).model_dump() == want


def test_model_dir_null_is_the_bundled_models():
    assert parse_settings(["--model-dir", "null"]).model_dir is None


@pytest.mark.parametrize(
    ("argv", "name"),
    [
        (["--port", "70000"], "port"),
        (["--max-batch-size", "0"], "max_batch_size"),
        (["--request-timeout-s", "0"], "request_timeout_s"),
        (["--max-queue", "many"], "max_queue"),
    ],
)
def test_bad_flag_exits_2_naming_the_setting(capsys, argv, name):
    with pytest.raises(SystemExit) as exc:
        parse_settings(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert f"{flag(name)} / {env_var(name)}:" in err
    assert argv[1] in err
    assert "Traceback" not in err


def test_bad_env_var_exits_2_naming_it(monkeypatch, capsys):
    monkeypatch.setenv("DS3D_MAX_LIFT_BATCH_SIZE", "5000")
    with pytest.raises(SystemExit) as exc:
        main([])  # fails in parsing, before uvicorn
    assert exc.value.code == 2
    assert "DS3D_MAX_LIFT_BATCH_SIZE" in capsys.readouterr().err


def test_unknown_flag_exits_2(capsys):
    with pytest.raises(SystemExit) as exc:
        parse_settings(["--no-such-setting", "1"])
    assert exc.value.code == 2
    assert "--no-such-setting" in capsys.readouterr().err


def test_settings_outside_the_cli_ignore_sys_argv(monkeypatch):
    """create_app's Settings() reads env vars only, never the process's command line."""
    monkeypatch.setattr(sys, "argv", ["ds3d-serve", "--port", "1"])
    assert Settings().port == 8000
    assert parse_settings().port == 1
