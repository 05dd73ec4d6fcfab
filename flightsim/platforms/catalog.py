"""The built-in platforms and the pose error model, registered by importing their modules."""
from flightsim.platforms import hover, lines, orbit, pose_errors, shots, tripod  # noqa: F401
