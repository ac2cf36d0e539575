"""BCF_* settings: parsing, .env files, errors from the commands, and the README's table matching the model."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest
from pydantic import ValidationError

from bcf.jobs.settings import Settings
from bcf_command import BCF, ONE_THREAD_ENV

README = Path(__file__).resolve().parent.parent / "README.md"


def test_tokens_are_split_and_trimmed(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("BCF_API_TOKENS", " alpha, beta ,,gamma ")
    monkeypatch.setenv("BCF_MAX_UPLOAD_MB", "3.5")
    settings = Settings(_env_file=None)
    assert settings.api_tokens == ["alpha", "beta", "gamma"] and settings.max_upload_mb == 3.5
    assert not settings.farm_mode


def test_a_dotenv_file_in_the_working_directory_is_read(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    for name in ("BCF_DATA_DIR", "BCF_QUEUE_URL"):
        monkeypatch.delenv(name, raising=False)
    (tmp_path / ".env").write_text(f"BCF_DATA_DIR={tmp_path / 'd'}\nBCF_QUEUE_URL=redis://queue:6379/2\n")
    monkeypatch.chdir(tmp_path)
    settings = Settings()
    assert settings.data_dir == tmp_path / "d" and settings.farm_mode
    assert settings.uploads_dir == tmp_path / "d" / "uploads"


def test_a_queue_url_that_is_not_redis_is_rejected() -> None:
    with pytest.raises(ValidationError, match="redis://"):
        Settings(_env_file=None, queue_url="amqp://rabbit")


def test_a_storage_url_must_be_s3_with_a_bucket() -> None:
    assert Settings(_env_file=None, storage_url="s3://farm/bcf").storage_url == "s3://farm/bcf"
    assert Settings(_env_file=None, storage_url=" ").storage_url is None  # blank: the data folder
    for url in ("/mnt/shared", "gs://bucket", "s3://", "s3:///prefix"):
        with pytest.raises(ValidationError, match="s3://bucket/prefix"):
            Settings(_env_file=None, storage_url=url)


def test_bad_settings_make_the_commands_exit_2_with_the_variable_named(tmp_path: Path) -> None:
    env = {**ONE_THREAD_ENV, "BCF_DATA_DIR": str(tmp_path), "BCF_MAX_UPLOAD_MB": "-1"}
    for command in ("serve", "worker"):
        result = subprocess.run([*BCF, command], env=env, cwd=tmp_path, capture_output=True, text=True,
                                timeout=120)
        assert result.returncode == 2, result.stderr
        assert "BCF_MAX_UPLOAD_MB" in result.stderr and result.stderr.startswith("bcf: error:")


def test_the_readme_documents_every_setting_with_its_default() -> None:
    rows = re.findall(r"^\| `BCF_([A-Z_]+)` \| ([^|]+) \|", README.read_text(), re.MULTILINE)
    documented = {name.lower(): default.strip() for name, default in rows}
    assert set(documented) == set(Settings.model_fields)
    defaults = Settings(_env_file=None, data_dir=Path("/x"))
    for name, text in documented.items():
        value = getattr(defaults, name)
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            assert float(text) == value, name
        elif value in (None, []):
            assert text == "none", name
