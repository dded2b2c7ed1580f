"""The CAN side of the service: DBC decoding of the BMS bus and encoding of the outputs."""

from service.bus.types import STATUS_FLAGS, PackSample, PackSnapshot

__all__ = ["STATUS_FLAGS", "PackSample", "PackSnapshot"]
