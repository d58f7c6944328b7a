"""`slamreloc serve`: relocalization as a gRPC service (protocol: `slamreloc.proto`).

Modules (the messages and their checks on untrusted input are `slamreloc.proto.messages`):
`maps` (the maps served: loaded once, reloaded atomically), `localize` (one Localize request),
`sessions` (a SLAM system's session: backend + relocalization plugin), `server` (the gRPC
server: authentication, limits, errors), `ray_serve` (the same service on Ray Serve).
Clients: `slamreloc.client` (Python), clients/cpp (C++).
"""

ENGINES = ("grpc", "ray")  # slamreloc's own gRPC server; the same service on Ray Serve
MAX_REPLICAS = 256  # replicas per map on Ray Serve (`--replicas`: checked whatever the engine)
TOKEN_ENV = "SLAMRELOC_TOKEN"  # the token every call must carry, where no token file is given
