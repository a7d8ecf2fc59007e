"""Render a MaterialX document with MaterialX's own GLSL renderer (the `materialx` package's
`GlslRenderer`, OpenGL through an X display: Xvfb and Mesa's llvmpipe where there is no GPU).

Run in a process of its own under `xvfb-run`, never imported by the tests' Python (Mesa's
llvmpipe and Dr.Jit each load an LLVM):

    xvfb-run -a python materialx_render.py SPEC_JSON OUT_NPY

SPEC_JSON holds `mtlx` (the document), `mesh` (an OBJ file, world coordinates), `camera`
(`origin`, `target`, `up`, `fov_x_deg`, `width`, `height`), `lights` (`direction` the light
travels, `irradiance` RGB in W/m^2: MaterialX's `directional_light`, whose `color` x
`intensity` is the irradiance it gives a surface facing it, as Mitsuba's `directional`) and
`supersample` (pixels rendered per side of each output pixel, averaged: a box filter as
layerfit's). OUT_NPY gets the linear RGB image, (height, width, 3) float32, row 0 at the top.

The environment is black: the hardware shading reads light from an environment map only through
a prefiltered or importance-sampled approximation, which the comparison leaves out. Images
(the baked masks and colours, linear EXR) are read through OpenImageIO; `fileTextureVerticalFlip`
puts a file's first row at v = 1, as MaterialX specifies (texture coordinate (0, 0) is the
image's lower-left corner)."""

from __future__ import annotations

import ctypes
import json
import math
import sys
from pathlib import Path

import MaterialX as mx
import numpy as np
import OpenImageIO as oiio
from MaterialX import PyMaterialXGenGlsl as mx_gen_glsl
from MaterialX import PyMaterialXGenShader as mx_gen
from MaterialX import PyMaterialXRender as mx_render
from MaterialX import PyMaterialXRenderGlsl as mx_glsl


class ExrLoader(mx_render.ImageLoader):
    """Linear float images (EXR) for MaterialX's image handler, read with OpenImageIO; `loaded`
    names the files read (an image the handler cannot load is black, silently)."""

    def __init__(self):
        super().__init__()
        self.loaded: set[str] = set()

    def supportedExtensions(self):
        return {"exr"}

    def loadImage(self, path):
        pixels = oiio.ImageBuf(path.asString()).get_pixels(oiio.FLOAT)
        self.loaded.add(Path(path.asString()).name)
        height, width, channels = pixels.shape
        image = mx_render.Image.create(width, height, channels, mx_render.BaseType.FLOAT)
        image.createResourceBuffer()
        data = np.ascontiguousarray(pixels, np.float32)
        ctypes.memmove(image.getResourceBuffer(), data.ctypes.data, data.nbytes)
        return image


def libraries():
    lib = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), lib)
    return lib


def light_nodes(lights: list[dict], lib):
    """One `directional_light` per light, in a document of their own."""
    doc = mx.createDocument()
    doc.setDataLibrary(lib)
    nodes = []
    for k, light in enumerate(lights):
        node = doc.addNode("directional_light", f"light{k}", "lightshader")
        node.setInputValue("direction", mx.Vector3(*light["direction"]))
        node.setInputValue("color", mx.Color3(*light["irradiance"]))
        node.setInputValue("intensity", 1.0)
        nodes.append(node)
    return doc, nodes


def main(spec_path: Path, out: Path) -> None:
    spec = json.loads(spec_path.read_text())
    mtlx, camera, ss = Path(spec["mtlx"]), spec["camera"], int(spec["supersample"])
    width, height = camera["width"] * ss, camera["height"] * ss
    lib = libraries()
    doc = mx.createDocument()
    mx.readFromXmlFile(doc, str(mtlx))
    doc.setDataLibrary(lib)

    generator = mx_gen_glsl.GlslShaderGenerator.create()
    context = mx_gen.GenContext(generator)
    context.registerSourceCodeSearchPath(mx.getDefaultDataSearchPath())
    generator.registerTypeDefs(doc)
    options = context.getOptions()
    # FIS with black maps: the NONE method's shader does not compile (`u_refractionTwoSided`
    # undeclared, MaterialX 1.39.5)
    options.hwSpecularEnvironmentMethod = (
        mx_gen.HwSpecularEnvironmentMethod.SPECULAR_ENVIRONMENT_FIS
    )
    options.hwMaxActiveLightSources = len(spec["lights"])
    options.hwSrgbEncodeOutput = False
    options.fileTextureVerticalFlip = True
    light_doc, lights = light_nodes(spec["lights"], lib)
    handler = mx_render.LightHandler.create()
    handler.registerLights(light_doc, lights, context)
    handler.setLightSources(lights)
    black = mx_render.createUniformImage(4, 2, 4, mx_render.BaseType.FLOAT, mx.Color4(0, 0, 0, 1))
    handler.setEnvRadianceMap(black)
    handler.setEnvIrradianceMap(black)
    (element,) = mx_gen.findRenderableElements(doc)
    shader = generator.generate("layerfit", element, context)

    renderer = mx_glsl.GlslRenderer.create(width, height, mx_render.BaseType.FLOAT)
    renderer.initialize()
    renderer.setLightHandler(handler)
    loader = ExrLoader()
    images = mx_glsl.GLTextureHandler.create(loader)
    images.setSearchPath(mx.FileSearchPath(str(mtlx.parent)))
    renderer.setImageHandler(images)
    geometry = renderer.getGeometryHandler()
    geometry.addLoader(mx_render.TinyObjLoader.create())
    if not geometry.loadGeometry(mx.FilePath(spec["mesh"]), False):
        raise SystemExit(f"cannot load {spec['mesh']}")
    view = renderer.getCamera()
    origin, target, up = (mx.Vector3(*camera[k]) for k in ("origin", "target", "up"))
    view.setViewMatrix(mx_render.Camera.createViewMatrix(origin, target, up))
    near = 0.01
    x = near * math.tan(math.radians(camera["fov_x_deg"]) / 2)
    y = x * height / width
    view.setProjectionMatrix(mx_render.Camera.createPerspectiveMatrix(-x, x, -y, y, near, 1e3))
    view.setWorldMatrix(mx.Matrix44.IDENTITY)
    renderer.createProgram(shader)
    renderer.validateInputs()
    renderer.render()
    image = renderer.captureImage(None)
    files = {
        Path(n.getInputValue("file")).name for n in doc.getNodes() if n.getCategory() == "image"
    }
    if files - loader.loaded:
        raise SystemExit(f"images not loaded: {sorted(files - loader.loaded)}")
    buffer = (ctypes.c_float * (width * height * 4)).from_address(image.getResourceBuffer())
    pixels = np.ctypeslib.as_array(buffer).reshape(height, width, 4)[::-1, :, :3]  # GL: bottom up
    pixels = pixels.reshape(height // ss, ss, width // ss, ss, 3).mean(axis=(1, 3))
    np.save(out, pixels.astype(np.float32))


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
