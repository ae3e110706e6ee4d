"""The station file's ``plant:`` block: where the station sits in the plant (ISA-95 names) and the
MQTT broker its results are streamed to (docs/integration.md, "MQTT").

Without the block the station publishes nothing and writes no outbox rows. Plain data: the
publisher (server/station/mqtt.py) builds its client from it.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, StringConstraints

# One level of an MQTT topic: no separators or wildcards, no leading '$' (broker topics).
TopicLevel = Annotated[str, StringConstraints(min_length=1, max_length=64,
                                              pattern=r"^[^/+#$\s][^/+#\s]*$")]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class MqttConfig(_Model):
    """The broker results are published to (MQTT 3.1.1, QoS 1)."""

    host: str = Field("127.0.0.1", min_length=1, description="broker host name or address")
    port: int = Field(1883, ge=1, le=65535, description="broker TCP port")
    keepalive_s: int = Field(10, ge=2, le=600,
                             description="MQTT keep-alive; the last will fires past 1.5x it")
    username: str | None = Field(None, max_length=200, description="broker user, if any")
    password_env: str | None = Field(
        None, max_length=200,
        description="environment variable holding the broker password (never the file)")
    poll_s: float = Field(1.0, gt=0, le=10,
                          description="the publisher looks for outbox rows after each "
                                      "answer and at least this often")
    keep_published_h: float = Field(24.0, ge=0, le=24 * 365,
                                    description="published outbox rows are deleted after this")


class PlantConfig(_Model):
    """The station's place in the ISA-95 hierarchy; its topics are
    ``<enterprise>/<site>/<area>/<line>/<station name>/mvpose/...``."""

    enterprise: TopicLevel
    site: TopicLevel
    area: TopicLevel
    line: TopicLevel
    mqtt: MqttConfig | None = Field(None, description="stream results to this broker")

    def topic_prefix(self, station: str) -> str:
        """``<enterprise>/<site>/<area>/<line>/<station>/mvpose``: the station's topic root."""
        return f"{self.enterprise}/{self.site}/{self.area}/{self.line}/{station}/mvpose"
