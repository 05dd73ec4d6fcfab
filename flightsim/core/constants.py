"""Constants shared by parts, the engine and studies."""
import math

ARCSEC = math.pi / (180.0 * 3600.0)  # [rad per arcsecond]
MODELS = ("exact", "nominal")  # georeferencing models (SPEC §5): the instrument as modelled, and the rigid array
