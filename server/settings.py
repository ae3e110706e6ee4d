"""Service settings from the environment (``MVPOSE_*``), read only when ``Settings()`` is built."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    """Everything the station server is configured with besides the station file itself.

    Build it explicitly (``Settings()`` reads the environment then, not at import) and hand it to
    :func:`server.app.create_app`; tests build their own with keyword arguments.
    """

    model_config = SettingsConfigDict(env_prefix="MVPOSE_", extra="forbid", frozen=True)

    station: Path | None = Field(None, description="station YAML file; recipes are seeded from it")
    station_name: str = Field(
        "default", description="chain/partition key in the store when no station file is given"
    )
    data_dir: Path = Field(Path("var"), description="SQLite database and image archive live here")
    database_url: str | None = Field(
        None, description="SQLAlchemy URL; default sqlite:///<data_dir>/mvpose.db"
    )
    # FULL: the WAL is fsynced at every commit, so a record survives a power cut once the PLC has
    # seen RESULT_VALID; NORMAL would only survive a process crash. The cost is one fsync per
    # insert (~0.25 ms measured on our VMs, see bench/bench_store.py).
    sqlite_synchronous: Literal["FULL", "NORMAL"] = "FULL"
    bootstrap_token: SecretStr | None = Field(
        None, description="ensured at start-up as an engineer token named 'bootstrap'"
    )
    images_dir: Path | None = Field(None, description="image archive; default <data_dir>/images")
    images_ok_every: int = Field(10, ge=1, description="archive 1 in N OK measurements' frames")
    images_quota_mb: float = Field(2048.0, gt=0, description="disk quota of the image archive")
    max_body_bytes: int = Field(1_048_576, ge=1024, description="largest accepted request body")
    software_version: str | None = Field(None, description="default: the installed mvpose version")
    control_socket: Path | None = Field(
        None, description="the station process's control channel; default <data_dir>/station.sock")

    @field_validator("database_url")
    @classmethod
    def _check_url(cls, v: str | None) -> str | None:
        if v is not None and not (v.startswith("sqlite") or v.startswith("postgresql")):
            raise ValueError(f"database_url must be sqlite or postgresql, got {v!r}")
        return v

    @property
    def resolved_database_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'mvpose.db').as_posix()}"

    @property
    def resolved_control_socket(self) -> Path:
        return self.control_socket or self.data_dir / "station.sock"

    @property
    def resolved_images_dir(self) -> Path:
        return self.images_dir or self.data_dir / "images"

    @property
    def resolved_software_version(self) -> str:
        if self.software_version:
            return self.software_version
        from importlib.metadata import PackageNotFoundError, version

        try:
            return version("mvpose")
        except PackageNotFoundError:
            return "0+unknown"
