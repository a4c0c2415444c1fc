// The relightable viewer of report.html: the captured maps on the sample plane, seen from the fixed
// camera above its centre and lit by a flash you move (drag: over the point under the pointer;
// wheel: nearer or farther) or by the prefiltered studio. Everything it needs is inside the page
// (maps as data URIs, the shader, the environment), so it runs from file:// with no network.
// The page's static report stays visible; where WebGL 2 is missing, the viewer says so.
(function () {
  "use strict";
  const root = document.getElementById("mdb-viewer");
  if (!root) return;
  const data = JSON.parse(document.getElementById("mdb-viewer-data").textContent);
  const fragmentSource = document.getElementById("mdb-viewer-fragment").textContent.trim();
  const canvas = root.querySelector("canvas");
  const status = root.querySelector(".mdb-viewer-status");
  const started = performance.now();
  const gl = canvas.getContext("webgl2", {preserveDrawingBuffer: true, antialias: false, premultipliedAlpha: false});
  if (!gl) {
    status.textContent = "WebGL 2 is not available in this browser: the static report above shows the capture.";
    canvas.hidden = true;
    return;
  }

  // --- the test hook: #viewer-test&light=x,y,z&mode=flash|env&normal=0|1&diffuse=0|1&specular=0|1&height=0|1
  const hash = new URLSearchParams(window.location.hash.replace(/^#/, "").replace(/^viewer-test&?/, ""));
  const testing = window.location.hash.indexOf("viewer-test") >= 0;

  const state = {
    light: data.light.slice(),
    environment: hash.get("mode") === "env",
    normalMap: hash.get("normal") !== "0",
    diffuse: hash.get("diffuse") !== "0",
    specular: hash.get("specular") !== "0",
    height: Boolean(data.height) && hash.get("height") === "1",  // the height map instead of the shading
  };
  if (hash.get("light")) state.light = hash.get("light").split(",").map(Number);

  function compile(type, source) {
    const shader = gl.createShader(type);
    gl.shaderSource(shader, source);
    gl.compileShader(shader);
    if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(shader));
    return shader;
  }
  const vertexSource = "#version 300 es\nvoid main() {\n" +
    "  vec2 corner = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));\n" +
    "  gl_Position = vec4(corner * 2.0 - 1.0, 0.0, 1.0);\n}\n";  // one triangle covers the canvas
  const program = gl.createProgram();
  gl.attachShader(program, compile(gl.VERTEX_SHADER, vertexSource));
  gl.attachShader(program, compile(gl.FRAGMENT_SHADER, fragmentSource));
  gl.linkProgram(program);
  if (!gl.getProgramParameter(program, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(program));
  gl.useProgram(program);
  const uniform = (name) => gl.getUniformLocation(program, name);

  function texture(unit, name, setup) {
    const handle = gl.createTexture();
    gl.activeTexture(gl.TEXTURE0 + unit);
    gl.bindTexture(gl.TEXTURE_2D, handle);
    setup();
    gl.uniform1i(uniform(name), unit);
  }
  function mapTexture(unit, name, image) {
    texture(unit, name, () => {
      // The bytes as stored: no colour management, no premultiplication, row 0 at the top.
      gl.pixelStorei(gl.UNPACK_COLORSPACE_CONVERSION_WEBGL, gl.NONE);
      gl.pixelStorei(gl.UNPACK_PREMULTIPLY_ALPHA_WEBGL, false);
      gl.pixelStorei(gl.UNPACK_FLIP_Y_WEBGL, false);
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA8, gl.RGBA, gl.UNSIGNED_BYTE, image);
      for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D, p, gl.NEAREST);
      for (const p of [gl.TEXTURE_WRAP_S, gl.TEXTURE_WRAP_T]) gl.texParameteri(gl.TEXTURE_2D, p, gl.CLAMP_TO_EDGE);
    });
  }
  function environmentTexture(unit) {
    const env = data.environment;
    const bytes = Uint8Array.from(atob(env.data), (c) => c.charCodeAt(0));
    texture(unit, "environmentMap", () => {
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA16F, env.width, env.height * env.levels, 0, gl.RGBA, gl.HALF_FLOAT,
                    new Uint16Array(bytes.buffer));
      for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D, p, gl.LINEAR);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.REPEAT);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    });
    gl.uniform1f(uniform("environmentLevels"), env.levels);
    gl.uniform3fv(uniform("irradiance"), new Float32Array(env.irradiance.flat()));
  }

  function draw() {
    gl.viewport(0, 0, canvas.width, canvas.height);
    gl.uniform2f(uniform("resolution"), canvas.width, canvas.height);
    gl.uniform1f(uniform("extent"), data.extent);
    gl.uniform3fv(uniform("cameraPosition"), data.camera);
    gl.uniform3fv(uniform("lightPosition"), state.light);
    gl.uniform1f(uniform("intensity"), data.intensity);
    gl.uniform1i(uniform("useNormalMap"), state.normalMap ? 1 : 0);
    gl.uniform1i(uniform("useDiffuse"), state.diffuse ? 1 : 0);
    gl.uniform1i(uniform("useSpecular"), state.specular ? 1 : 0);
    gl.uniform1i(uniform("environmentMode"), state.environment ? 1 : 0);
    gl.uniform1i(uniform("showHeight"), state.height ? 1 : 0);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
    const [x, y, z] = state.light;
    status.textContent = state.height ? heightStatus()
      : state.environment ? "studio environment (prefiltered)"
        : `flash at (${x.toFixed(2)}, ${y.toFixed(2)}, ${z.toFixed(2)}) [patch half-widths]`;
  }
  function heightStatus() {
    const {black, white} = data.height;
    if (typeof black !== "number" || typeof white !== "number") return "height map";
    return `height map: black ${black.toPrecision(3)}, white ${white.toPrecision(3)} [patch half-widths]`;
  }

  function controls() {
    const bind = (name, key) => {
      const input = root.querySelector(`[name=${name}]`);
      input.checked = state[key];
      input.addEventListener("change", () => { state[key] = input.checked; draw(); });
    };
    bind("normal", "normalMap");
    bind("diffuse", "diffuse");
    bind("specular", "specular");
    if (data.height) bind("height", "height");
    for (const input of root.querySelectorAll("[name=light]")) {
      input.checked = (input.value === "env") === state.environment;
      input.addEventListener("change", () => { state.environment = input.value === "env"; draw(); });
    }
    let dragging = false;
    const follow = (event) => {
      const box = canvas.getBoundingClientRect();
      state.light[0] = ((event.clientX - box.left) / box.width * 2 - 1) * data.extent;
      state.light[1] = (1 - (event.clientY - box.top) / box.height * 2) * data.extent;
      state.environment = false;
      for (const input of root.querySelectorAll("[name=light]")) input.checked = input.value === "flash";
      draw();
    };
    canvas.addEventListener("pointerdown", (event) => { dragging = true; canvas.setPointerCapture(event.pointerId); follow(event); });
    canvas.addEventListener("pointermove", (event) => { if (dragging) follow(event); });
    canvas.addEventListener("pointerup", () => { dragging = false; });
    canvas.addEventListener("wheel", (event) => {
      event.preventDefault();
      state.light[2] = Math.min(20, Math.max(0.2, state.light[2] * Math.exp(event.deltaY * 0.001)));
      draw();
    }, {passive: false});
  }

  const names = ["normal", "diffuse", "roughness", "specular"];
  const sources = names.map((name) => [name + "Map", data.maps[name]]);
  if (data.height) sources.push(["heightMap", data.height.map]);  // 8-bit grey
  let pending = sources.length;
  // The environment takes the unit after the maps'; without a height map, heightMap samples unit 0 unseen.
  sources.forEach(([name, source], unit) => {
    const image = new Image();
    image.onload = () => {
      mapTexture(unit, name, image);
      if (--pending === 0) ready();
    };
    image.src = source;
  });

  function ready() {
    environmentTexture(sources.length);
    controls();
    draw();
    gl.finish();
    root.dataset.firstFrameMs = (performance.now() - started).toFixed(1);
    if (testing) {
      const pixels = new Uint8Array(canvas.width * canvas.height * 4);
      gl.readPixels(0, 0, canvas.width, canvas.height, gl.RGBA, gl.UNSIGNED_BYTE, pixels);
      let text = "";
      for (let i = 0; i < pixels.length; i += 0x8000) text += String.fromCharCode.apply(null, pixels.subarray(i, i + 0x8000));
      const out = document.createElement("pre");
      out.id = "mdb-viewer-readback";
      out.dataset.width = canvas.width;
      out.dataset.height = canvas.height;
      out.dataset.firstFrameMs = root.dataset.firstFrameMs;
      out.textContent = btoa(text);  // RGBA rows from the bottom, as readPixels gives them
      document.body.appendChild(out);
    }
  }
})();
