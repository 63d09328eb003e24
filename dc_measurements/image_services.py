"""image_services: the original DC's image services, served by one lifecycle node with the Camera's code.

``dc/service/detect_barcodes`` (dc_interfaces/srv/DetectBarcode), ``dc/service/draw_image``
(DrawImage) and ``dc/service/save_image`` (SaveImage) in the server's namespace (``/dc/service/…``
without one, as the original's), for nodes written against the original. DC's
own Camera measurement does not need them (it reads and draws in-process). dc-bringup starts this
server when the parameter file has an ``image_services`` section::

    image_services:
      ros__parameters:
        services: ["detect_barcodes", "draw_image", "save_image"]

``python -m dc_measurements.image_services PARAMS [--autostart]``.
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from dataclasses import dataclass, fields
from typing import Any

from dc_core.errors import ConfigError
from dc_core.lifecycle import ManagedServer, run_server
from dc_core.node_params import ServerNodeParams
from dc_core.params import did_you_mean, param, parse_params
from dc_core.topics import topic_problem

NODE_NAME = "image_services"
SERVICES = ("detect_barcodes", "draw_image", "save_image")


def _services_problem(names: list[str]) -> str | None:
    unknown = [n for n in names if n not in SERVICES]
    return f"services among {list(SERVICES)} (unknown: {unknown})" if unknown else None


@dataclass(frozen=True, kw_only=True)
class ImageServicesParams(ServerNodeParams):
    services: list[str] = param(list(SERVICES), doc="The services to offer", check=_services_problem)
    # Relative, as DC's topics: two robots' image_services under --namespace r1 and r2 offer
    # /r1/dc/service/… and /r2/dc/service/…, not both the same /dc/service/… services.
    service_namespace: str = param(
        "dc/service",
        doc="Where the services are: relative, in the server's namespace (/dc/service without one, the original's); "
        "absolute when written so",
        check=lambda name: topic_problem(name) and "a ROS 2 name",
    )
    detection_modules: list[str] = param(
        ["barcode"], doc='What detect_barcodes reads: "qr" and/or "barcode" (as the Camera measurement)'
    )
    save_roots: list[str] = param(
        [],
        doc="Folders save_image may write in ($ENV); empty: measurement_server's save_local_base_path of the same file",
    )


@dataclass(frozen=True)
class ImageServicesConfig:
    node: ImageServicesParams
    warnings: list[str]


def parse_image_services(section: dict[str, Any], path: str = NODE_NAME) -> ImageServicesConfig:
    if not isinstance(section, dict):
        raise ConfigError(path, f"expected a mapping, got {section!r}")
    known = {f.name for f in fields(ImageServicesParams)}
    for key in section:
        if key not in known:
            raise ConfigError(f"{path}.{key}", "unknown parameter" + did_you_mean(str(key), known))
    node = parse_params(ImageServicesParams, section, path)
    from dc_measurements.camera import _modules_problem

    problem = _modules_problem(node.detection_modules)
    if problem:
        raise ConfigError(f"{path}.detection_modules", f"expected {problem}")
    return ImageServicesConfig(node, [])


def service_name(service_namespace: str, name: str) -> str:
    """The name a service is created with: relative to the node's namespace unless ``service_namespace`` is absolute."""
    base = service_namespace.rstrip("/")
    if base:
        return f"{base}/{name}"
    return "/" + name if service_namespace.startswith("/") else name


def image_message(array: Any, header: Any = None) -> Any:
    """A bgr8 (or mono8) sensor_msgs/Image of an OpenCV array."""
    from sensor_msgs.msg import Image

    message = Image()
    if header is not None:
        message.header = header
    message.height, message.width = array.shape[:2]
    message.encoding = "bgr8" if array.ndim == 3 else "mono8"
    message.step = array.shape[1] * (3 if array.ndim == 3 else 1)
    message.data = array.tobytes()
    return message


class ImageServices(ManagedServer):
    def __init__(self, params_file: str) -> None:
        super().__init__(NODE_NAME, params_file)
        self.config: ImageServicesConfig | None = None
        self._detector: Any = None
        self._save_roots: Any = None
        self._offered_services: list[Any] = []

    def configure_server(self) -> None:
        sections = self.read_params_file()
        self.config = parse_image_services(sections[NODE_NAME])
        self.apply_node_params(self.config.node, self.config.warnings)
        self._save_roots = save_confinement(self.config.node, sections.get("measurement_server"))
        self.get_logger().info(f"save_image writes only in {self._save_roots.describe()}")
        from dc_measurements.camera.detection import BarcodeDetector

        self._detector = BarcodeDetector(self.config.node.detection_modules)

    def activate_server(self) -> None:
        from dc_interfaces.srv import DetectBarcode, DrawImage, SaveImage

        assert self.config is not None
        handlers = {
            "detect_barcodes": (DetectBarcode, self._detect),
            "draw_image": (DrawImage, self._draw),
            "save_image": (SaveImage, self._save),
        }
        for name in self.config.node.services:
            service_type, handler = handlers[name]
            self._offered_services.append(
                self.create_service(service_type, service_name(self.config.node.service_namespace, name), handler)
            )
        # As rcl resolved them (namespace, remaps): the names a client must call.
        self.get_logger().info(f"serving {', '.join(s.service_name for s in self._offered_services)}")

    def deactivate_server(self) -> None:
        for service in self._offered_services:
            self.destroy_service(service)
        self._offered_services.clear()

    def cleanup_server(self) -> None:
        self._detector = None
        self.config = None

    # -- the services --------------------------------------------------------------------------------
    def _frame(self, message: Any) -> Any:
        from dc_measurements.camera.images import image_to_array

        return image_to_array(message)

    def _detect(self, request: Any, response: Any) -> Any:
        from dc_interfaces.msg import Barcode
        from dc_measurements.camera.images import ImageError

        try:
            detections = self._detector.detect(self._frame(request.frame))
        except ImageError as exc:
            self.get_logger().error(f"detect_barcodes: {exc}")
            return response
        for d in detections:
            response.barcodes.append(
                Barcode(
                    data=d.data,
                    type=d.type,
                    top=min(d.top, 65535),
                    left=min(d.left, 65535),
                    width=min(d.width, 65535),
                    height=min(d.height, 65535),
                )
            )
        return response

    def _draw(self, request: Any, response: Any) -> Any:
        import cv2

        from dc_measurements.camera.images import ImageError

        if request.shape != "rectangle":
            self.get_logger().error(f"draw_image: shape {request.shape!r} is not supported (only 'rectangle')")
            response.success = False
            return response
        try:
            image = self._frame(request.frame)
        except ImageError as exc:
            self.get_logger().error(f"draw_image: {exc}")
            response.success = False
            return response
        if image.ndim == 2:
            image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        color = tuple(int(c) for c in request.color[:3]) if len(request.color) >= 3 else (255, 0, 0)
        thickness = int(request.box_thickness) or 2
        top_left = (int(request.box_left), int(request.box_top))
        bottom_right = (int(request.box_left + request.box_width), int(request.box_top + request.box_height))
        cv2.rectangle(image, top_left, bottom_right, color, thickness)
        if request.text:
            scale = float(request.font_scale) or 0.8
            cv2.putText(
                image,
                request.text,
                (top_left[0], max(0, top_left[1] - 9)),
                int(request.font_txt),
                scale,
                color,
                int(request.font_thickness) or 2,
            )
        response.frame = image_message(image, request.frame.header)
        response.success = True
        return response

    def _save(self, request: Any, response: Any) -> Any:
        import cv2

        from dc_core.confined_files import FileRefused
        from dc_measurements.camera.images import ImageError

        try:
            # Any node on the graph can call the service: the path is confined like the files a record names.
            real = self._save_roots.check_path(request.path)
            image = self._frame(request.frame)
            encoded_ok, encoded = cv2.imencode(os.path.splitext(real)[1] or ".png", image)
            if not encoded_ok:
                raise ImageError(f"cannot encode the frame as {os.path.splitext(real)[1]!r}")
            write_replacing(real, encoded.tobytes())
            response.success = True
        except FileRefused as exc:
            self.get_logger().warning(f"save_image refused: {exc}")
            response.success = False
        except (ImageError, OSError, cv2.error) as exc:
            self.get_logger().error(f"save_image {request.path!r}: {exc}")
            response.success = False
        return response


def save_confinement(node: ImageServicesParams, measurement_server: dict[str, Any] | None) -> Any:
    """Where save_image may write: ``save_roots`` ($ENV expanded), else the measurement server's save folder."""
    from dc_core.confined_files import Confinement, default_roots
    from dc_core.paths import expand_env

    if node.save_roots:
        roots = [expand_env(root, f"{NODE_NAME}.save_roots[{i}]") for i, root in enumerate(node.save_roots)]
    else:
        roots = default_roots(measurement_server)
    return Confinement(roots)


def write_replacing(path: str, data: bytes) -> None:
    """Write ``data`` to a new file beside ``path`` and rename it over ``path``: a symbolic or hard link
    already at ``path`` is replaced, never written through."""
    folder = os.path.dirname(path)
    os.makedirs(folder, mode=0o700, exist_ok=True)
    fd, temporary = tempfile.mkstemp(dir=folder, prefix=".save_image-")
    try:
        with os.fdopen(fd, "wb") as out:
            out.write(data)
        os.replace(temporary, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(temporary)
        raise


def main() -> int:
    return run_server(ImageServices)


if __name__ == "__main__":
    sys.exit(main())
