"""The Siemens S7 backend of the link seam: mvpose as an S7 client (PUT/GET) of the line's PLC,
polling a trigger DB and writing a result DB laid out as the fieldbus layout
(docs/s7.md; docs/fieldbus-layout.md).

- :mod:`.poller`: the poll cycle as data (what to write, the PDU and DB checks, backoff);
- :mod:`.transport`: python-snap7's asyncio client, wrapped; :mod:`.link`: :class:`S7Link`;
- :mod:`.settings`: the station file's ``links.s7``;
- :mod:`.twin`: a CPU (python-snap7's server) with the two DBs and the twin's port on it.
"""

from .link import S7Link
from .settings import S7LinkConfig

__all__ = ["S7Link", "S7LinkConfig"]
