"""`slamreloc serve --engine ray` (slamreloc.service.ray_serve) against a local Ray instance.

One module-scoped deployment: the session's small map served under two names, two replicas
each, on a 2-CPU local Ray instance; every check goes through plain gRPC (the generated stub) to
Serve's gRPC proxy, and poses are compared with the in-process `service.localize`.
"""

from __future__ import annotations

import asyncio
import signal
import socket
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("ray.serve", reason="Ray Serve is not installed (pip install 'ray[serve]')")
grpc = pytest.importorskip("grpc")

from slamreloc.errors import InputError
from slamreloc.proto import PROTOCOL
from slamreloc.proto import relocalizer_pb2 as pb
from slamreloc.proto.messages import ERROR_METADATA_KEY, ServiceError
from slamreloc.proto.relocalizer_pb2_grpc import RelocalizerStub

MAPS = ("alpha", "beta")
REPLICAS = 2
DEPLOY_FILE = Path(__file__).resolve().parents[1] / "deploy" / "ray-serve.yaml"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def service(small_map, scene_dir):
    """The deployment, a stub on its gRPC port, and two test images with in-process answers.
    The driver (this process) holds input bounds of its own, which the map replicas must hold
    too (round 28, J3): no more pixels than the test images' and sides down to 8 pixels, while
    the environment the replicas inherit says the defaults."""
    from slamreloc.datasets import load_dataset
    from slamreloc.io import limits
    from slamreloc.service import ray_serve
    from slamreloc.service.localize import localize
    from slamreloc.service.maps import ServedMap

    frames = load_dataset(scene_dir).frames("test")[:2]
    requests = [pb.LocalizeRequest(image=pb.Image(encoded=f.image_path.read_bytes()))
                for f in frames]
    served = ServedMap.load("reference", small_map.root)
    expected = [localize(served, r) for r in requests]
    import cv2

    height, width = cv2.imdecode(np.frombuffer(requests[0].image.encoded, np.uint8),
                                 cv2.IMREAD_UNCHANGED).shape[:2]
    port = free_port()
    t0 = time.perf_counter()
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("SLAMRELOC_MAX_IMAGE_PIXELS", str(limits.InputLimits().max_image_pixels))
        mp.setenv("SLAMRELOC_MIN_IMAGE_SIDE", str(limits.InputLimits().min_image_side))
        mp.setattr(limits, "_current", replace(limits.limits(), max_image_pixels=width * height,
                                               min_image_side=8))
        deployment = ray_serve.deploy({name: small_map.root for name in MAPS},
                                      replicas=REPLICAS, grpc_port=port, http_port=free_port(),
                                      num_cpus=2, log_to_driver=False)
        try:
            print(f"\nray serve: ray.init + serve.start {deployment.ray_start_s:.1f} s, deploy "
                  f"{deployment.deploy_s:.1f} s, total {time.perf_counter() - t0:.1f} s")
            channel = grpc.insecure_channel(f"127.0.0.1:{port}")
            yield SimpleNamespace(stub=RelocalizerStub(channel), deployment=deployment,
                                  requests=requests, expected=expected, served=served,
                                  size=(width, height))
            channel.close()
        finally:
            ray_serve.shutdown()
    import ray

    assert not ray.is_initialized()


def pose(response: pb.LocalizeResponse) -> np.ndarray:
    t = response.world_from_cam
    return np.array([t.tx, t.ty, t.tz, t.qx, t.qy, t.qz, t.qw])


def routed(request: pb.LocalizeRequest, name: str) -> pb.LocalizeRequest:
    out = pb.LocalizeRequest()
    out.CopyFrom(request)
    out.map = name
    return out


def refusal(call) -> tuple[grpc.StatusCode, str, str]:
    """(code, details, slamreloc-error) of a call that must fail."""
    with pytest.raises(grpc.RpcError) as info:
        call()
    err = info.value
    kind = dict(err.trailing_metadata() or ()).get(ERROR_METADATA_KEY, "")
    return err.code(), err.details(), kind


def assert_same_answer(got: pb.LocalizeResponse, want: pb.LocalizeResponse) -> None:
    assert want.localized, "the in-process reference must localize the test image"
    assert got.localized
    assert np.allclose(pose(got), pose(want), rtol=0, atol=1e-9), (pose(got), pose(want))
    assert (got.num_inliers, got.num_correspondences, got.num_keypoints) == \
        (want.num_inliers, want.num_correspondences, want.num_keypoints)
    assert got.map_version == want.map_version


def test_localize_is_routed_by_map_name_and_equals_in_process(service):
    for name in MAPS:
        for request, want in zip(service.requests, service.expected):
            assert_same_answer(service.stub.Localize(routed(request, name), timeout=60), want)
    # the two images have different poses: a router that answered from a cache would fail
    assert not np.allclose(pose(service.expected[0]), pose(service.expected[1]), atol=1e-3)


def test_unknown_map_is_not_found_with_the_error_kind(service):
    code, details, kind = refusal(lambda: service.stub.Localize(
        routed(service.requests[0], "gamma"), timeout=30))
    assert (code, kind) == (grpc.StatusCode.NOT_FOUND, "UNKNOWN_MAP")
    assert "gamma" in details and "alpha, beta" in details
    # with two maps, an empty name does not pick one
    code, _, kind = refusal(lambda: service.stub.Localize(service.requests[0], timeout=30))
    assert (code, kind) == (grpc.StatusCode.NOT_FOUND, "UNKNOWN_MAP")


def test_corrupt_image_is_invalid_argument_as_in_process(service):
    png = service.requests[0].image.encoded
    request = pb.LocalizeRequest(map="beta", image=pb.Image(encoded=png[: len(png) // 3]))
    with pytest.raises(ServiceError) as local:
        from slamreloc.service.localize import localize

        localize(service.served, request)
    code, details, kind = refusal(lambda: service.stub.Localize(request, timeout=30))
    assert code == grpc.StatusCode.INVALID_ARGUMENT == local.value.grpc_code
    assert kind == local.value.kind_name == "BAD_IMAGE"
    assert details == local.value.message
    raw = pb.LocalizeRequest(map="alpha", image=pb.Image(raw=pb.RawImage(
        width=64, height=48, channels=3, data=b"\0" * 10)))
    code, _, kind = refusal(lambda: service.stub.Localize(raw, timeout=30))
    assert (code, kind) == (grpc.StatusCode.INVALID_ARGUMENT, "BAD_IMAGE")


def test_request_over_the_size_bound_is_resource_exhausted(service):
    from slamreloc.service.ray_app import MAX_REQUEST_BYTES

    big = pb.LocalizeRequest(map="alpha", image=pb.Image(encoded=bytes(MAX_REQUEST_BYTES + 1)))
    code, _, _ = refusal(lambda: service.stub.Localize(big, timeout=60))
    assert code == grpc.StatusCode.RESOURCE_EXHAUSTED


def test_the_drivers_input_bounds_hold_in_every_replica(service):
    """Round 28, J3: `slamreloc --limit max_image_pixels=1000 serve --engine ray` answered a
    320 x 240 Localize the gRPC engine refuses: the bounds held in the driver only, the
    replicas read their own environment. Every replica now answers as the driver's bounds
    say (as `service.localize` in this process), lowered (a pixel more than the bound) and
    raised (sides of 9 pixels under the default 16) alike."""
    import cv2

    from slamreloc.service.localize import localize

    width, height = service.size
    rng = np.random.default_rng(0)
    for w, h, refused in ((width + 1, height, True), (12, 9, False)):
        image = cv2.imencode(".png", rng.integers(0, 255, (h, w, 3), np.uint8))[1].tobytes()
        request = pb.LocalizeRequest(image=pb.Image(encoded=image))
        try:
            local = localize(service.served, request)
        except ServiceError as err:
            local = err
        if refused:
            assert isinstance(local, ServiceError) and local.kind_name == "TOO_LARGE"
            assert f"{(width + 1) * height} pixels, over the {width * height} pixels limit " \
                "(max_image_pixels" in local.message
        else:  # the driver's 8 pixels a side hold, not the replicas' environment's 16
            assert not (isinstance(local, ServiceError) and "a side" in local.message)
        for i in range(2 * REPLICAS):  # Serve spreads them over the replicas
            call = lambda: service.stub.Localize(routed(request, MAPS[i % 2]), timeout=60)
            if isinstance(local, ServiceError):
                code, details, kind = refusal(call)
                assert (code, details, kind) == (local.grpc_code, local.message,
                                                 local.kind_name)
            else:
                got = call()
                got.ClearField("timings")  # all else as in this process
                local.ClearField("timings")
                assert got == local


def test_list_maps_health_and_reload(service):
    maps = service.stub.ListMaps(pb.ListMapsRequest(), timeout=30).maps
    assert sorted(m.name for m in maps) == sorted(MAPS)
    assert {m.version for m in maps} == {service.served.version}
    assert all(m.num_points > 0 and m.path == str(service.served.path.resolve()) for m in maps)
    health = service.stub.Health(pb.HealthRequest(), timeout=30)
    assert health.serving and health.protocol == PROTOCOL and health.num_maps == len(MAPS)
    assert health.num_requests >= 1 and health.uptime_s > 0
    reloaded = service.stub.ReloadMap(pb.ReloadMapRequest(map="alpha"), timeout=60)
    assert not reloaded.changed and reloaded.map.version == service.served.version
    code, _, kind = refusal(lambda: service.stub.ReloadMap(pb.ReloadMapRequest(map="x"),
                                                           timeout=30))
    assert (code, kind) == (grpc.StatusCode.NOT_FOUND, "UNKNOWN_MAP")


def test_concurrent_requests_on_two_replicas_all_succeed(service):
    from ray import serve

    app = serve.status().applications[service.deployment.app_name]
    for name in MAPS:
        replicas = app.deployments[f"map-{name}"].replica_states
        assert replicas.get("RUNNING") == REPLICAS, replicas
    jobs = [(routed(service.requests[i % 2], MAPS[(i // 2) % 2]), service.expected[i % 2])
            for i in range(8)]
    with ThreadPoolExecutor(len(jobs)) as pool:
        answers = list(pool.map(lambda job: service.stub.Localize(job[0], timeout=120), jobs))
    for got, (_, want) in zip(answers, jobs):
        assert_same_answer(got, want)


def test_session_is_left_to_the_native_server(service):
    opened = iter([pb.SessionRequest(open=pb.SessionOpen(map="alpha"))])
    updates = []
    code, details, kind = refusal(lambda: updates.extend(service.stub.Session(opened,
                                                                             timeout=30)))
    assert (code, kind) == (grpc.StatusCode.FAILED_PRECONDITION, "FAILED_PRECONDITION")
    assert "the grpc engine (`engine` grpc)" in details  # the setting, as library messages say
    # as the native server refuses a session it cannot open: the error, then the status
    assert [u.WhichOneof("message") for u in updates] == ["error"]
    assert (updates[0].error.kind, updates[0].error.message) == (pb.FAILED_PRECONDITION, details)


# ---- without Ray running ---------------------------------------------------------------------
class FakeContext:
    """What the router uses of RayServegRPCContext."""

    def __init__(self, metadata=()):
        self.metadata, self.code, self.details, self.trailing = list(metadata), None, "", []

    def invocation_metadata(self):
        return self.metadata

    def set_code(self, code):
        self.code = code

    def set_details(self, details):
        self.details = details

    def set_trailing_metadata(self, metadata):
        self.trailing = metadata


def test_router_checks_the_token():
    from slamreloc.service.ray_app import Router

    token = "t" * 24
    router = Router.func_or_class({}, token)
    for metadata in ([], [("authorization", "Bearer wrong")]):
        context = FakeContext(metadata)
        asyncio.run(router.Health(pb.HealthRequest(), context))
        assert context.code == grpc.StatusCode.UNAUTHENTICATED
        assert context.trailing == [(ERROR_METADATA_KEY, "UNAUTHENTICATED")]
    for scheme in ("Bearer", "bearer", "BEARER"):  # the scheme in any case, as the gRPC engine
        context = FakeContext([("authorization", f"{scheme} {token}")])
        assert asyncio.run(router.Health(pb.HealthRequest(), context)).serving
        assert context.code is None


def test_deploy_file_is_a_valid_serve_config(small_map):
    import yaml
    from ray.serve._private.utils import import_attr
    from ray.serve.deployment import Application
    from ray.serve.schema import ServeDeploySchema

    config = ServeDeploySchema.model_validate(yaml.safe_load(DEPLOY_FILE.read_text()))
    assert config.grpc_options.grpc_servicer_functions == [
        "slamreloc.proto.relocalizer_pb2_grpc.add_RelocalizerServicer_to_server"]
    (app,) = config.applications
    builder = import_attr(app.import_path)
    args = {**app.args, "maps": {name: str(small_map.root) for name in app.args["maps"]}}
    assert isinstance(builder(args), Application)
    with pytest.raises(InputError, match="not a map folder"):  # the file's own example paths
        builder(app.args)
    with pytest.raises(InputError, match="unknown"):
        builder({**args, "replica": 2})


def test_serve_forever_says_where_blocks_and_shuts_down(monkeypatch, capsys, small_map):
    """The CLI's entry (`slamreloc serve --engine ray`), with deploy and the wait stubbed."""
    from slamreloc.service import ray_serve

    calls = []
    monkeypatch.setattr(ray_serve, "deploy", lambda *a, **k: calls.append(("deploy", a, k)))
    monkeypatch.setattr(ray_serve, "shutdown", lambda: calls.append(("shutdown",)))
    monkeypatch.setattr(signal, "signal", lambda *a: None)  # keep pytest's SIGTERM handler

    def ctrl_c():
        calls.append(("waited",))
        raise KeyboardInterrupt

    monkeypatch.setattr(ray_serve, "_block", ctrl_c)
    ray_serve.serve_forever({"alpha": small_map.root}, replicas=3, host="127.0.0.1", port=9321)
    assert capsys.readouterr().out == "listening on 127.0.0.1:9321 (ray serve)\n"
    assert [c[0] for c in calls] == ["deploy", "waited", "shutdown"]
    assert calls[0][1] == ({"alpha": small_map.root}, 3, "127.0.0.1", 9321)


def test_sigterm_stops_the_ray_engine_as_ctrl_c_does(small_map, tmp_path):
    """Round 37, V7: `ray.init` put Ray's native SIGTERM handler in place of the program's, so
    `kill` aborted `slamreloc serve --engine ray` with a stack dump (exit -6) and left Ray's
    agents running; SIGTERM stops Serve and Ray as Ctrl-C does."""
    import subprocess
    import sys

    log, token = tmp_path / "serve.log", tmp_path / "token"
    token.write_text("a-token-for-this-test\n")
    with open(log, "w") as out:
        server = subprocess.Popen(
            [sys.executable, "-m", "slamreloc.cli", "serve", str(small_map.root), "--engine",
             "ray", "--port", "0", "--token-file", str(token)], stdout=out,
            stderr=subprocess.STDOUT, text=True)
        try:
            deadline = time.monotonic() + 240
            while "listening on" not in log.read_text() and time.monotonic() < deadline:
                assert server.poll() is None, log.read_text()
                time.sleep(1)
            assert "listening on" in log.read_text(), log.read_text()
            server.send_signal(signal.SIGTERM)
            code = server.wait(180)
        finally:
            if server.poll() is None:
                server.kill()
    text = log.read_text()
    assert code == 0, text
    assert "slamreloc serve: stopping (ray serve)" in text
    assert "SIGTERM received" not in text
