"""gmt.v1.ModelAdmin: model management over gRPC, authorised per call by `gmt.service.admin`'s rule."""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import TypeVar

from gmt.service import admin
from gmt.service.core import Core
from gmt.service.grpc import convert
from gmt.service.grpc.servicer import PolicyServicer
from gmt.service.views import ModelView
from gmt.v1 import admin_pb2 as apb
from gmt.v1 import admin_pb2_grpc
from gmt.v1 import policy_pb2 as pb

T = TypeVar("T")


def model_versions(v: ModelView) -> pb.ModelInfo:
    """A model's state after a change: its name and version table (everything, while it has a version)."""
    return convert.model_info(v) if v.versions else pb.ModelInfo(name=v.name)


class ModelAdminServicer(admin_pb2_grpc.ModelAdminServicer):
    """The ModelAdmin service over one core; calls are timed and mapped to status codes as PolicyService's."""

    def __init__(self, core: Core, policy: PolicyServicer) -> None:
        self.core = core
        self.policy = policy  # its `_unary`: deadline, metrics, error mapping

    async def _call(self, method: str, context, call: Callable[[], Awaitable[T]]) -> T:
        async def authorised() -> T:
            md = {k: v for k, v in context.invocation_metadata() or ()}
            auth = md.get("authorization")
            admin.authorize(
                self.core.settings,
                auth.decode() if isinstance(auth, bytes) else auth,
                admin.grpc_peer_host(context.peer()),
                any(h in md for h in admin.PROXY_HEADERS),
            )
            return await call()

        return await self.policy._unary(f"ModelAdmin.{method}", context, authorised)

    async def LoadVersion(self, request: apb.LoadVersionRequest, context) -> apb.LoadVersionResponse:
        async def call():
            v = await self.core.load_version(request.name, request.path, request.fingerprint or None)
            return apb.LoadVersionResponse(name=request.name, version=pb.ModelVersion(**vars(v)))

        return await self._call("LoadVersion", context, call)

    async def Promote(self, request: apb.PromoteRequest, context) -> pb.ModelInfo:
        async def call():
            share = request.share if request.HasField("share") else 1.0
            return model_versions(await self.core.promote(request.name, request.version, share))

        return await self._call("Promote", context, call)

    async def Drain(self, request: apb.DrainRequest, context) -> pb.ModelInfo:
        async def call():
            return model_versions(await self.core.drain(request.name, request.version))

        return await self._call("Drain", context, call)

    async def Unload(self, request: apb.UnloadRequest, context) -> pb.ModelInfo:
        async def call():
            return model_versions(await self.core.unload(request.name, request.version, request.force))

        return await self._call("Unload", context, call)
