"""slamreloc's wire protocol: `relocalizer.proto` (package `slamreloc.v1`), the Python code
protoc generates from it, and `messages` (its messages <-> slamreloc's types, with the checks
on untrusted input; shared by the server and the clients). Regenerate the generated code
after editing the .proto, from the repository root:

    python -m grpc_tools.protoc -I. --python_out=. --pyi_out=. --grpc_python_out=. \\
        slamreloc/proto/relocalizer.proto

(the test suite checks the generated files match the .proto). C++ clients compile the same
.proto (clients/cpp)."""

from pathlib import Path

PROTO_FILE = Path(__file__).with_name("relocalizer.proto")
PROTOCOL = "slamreloc.v1"
