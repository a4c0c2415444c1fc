#version 300 es
// The `physical` convention of docs/ARCHITECTURE.md section 4, as render/shading.py and render/reference.py have
// it, for one pixel of the sample plane seen from the fixed camera and lit by a point light
// (flash mode), or lit by the prefiltered studio environment (environment mode).
precision highp float;
precision highp int;

uniform sampler2D normalMap;     // (n + 1) / 2, OpenGL convention
uniform sampler2D diffuseMap;    // sRGB-encoded
uniform sampler2D roughnessMap;  // linear
uniform sampler2D specularMap;   // sRGB-encoded
uniform sampler2D heightMap;     // height.png's range as [0, 1], 8-bit grey
uniform vec2 resolution;         // canvas size [pixels]
uniform float extent;            // half-width of the framed sample [patch half-widths]
uniform vec3 cameraPosition;     // [patch half-widths]
uniform vec3 lightPosition;      // [patch half-widths]
uniform float intensity;         // radiant intensity of the flash [W/sr]
uniform int useNormalMap;        // 0: flat normals
uniform int useDiffuse;          // 0: no diffuse lobe
uniform int useSpecular;         // 0: no specular lobe
uniform int environmentMode;     // 1: the prefiltered studio instead of the flash
uniform int showHeight;          // 1: the height map's grey levels instead of the shading
uniform sampler2D environmentMap;  // prefiltered radiance, equirectangular, LEVELS rows of bands
uniform vec3 irradiance[9];      // the environment's irradiance as order-2 spherical harmonics
uniform float environmentLevels;

out vec4 fragColor;

const float PI = 3.14159265358979;
const float MIN_ROUGHNESS = 1e-3;

float srgbToLinear(float x) {
    return x <= 0.04045 ? x / 12.92 : pow((x + 0.055) / 1.055, 2.4);
}
vec3 srgbToLinear(vec3 x) { return vec3(srgbToLinear(x.r), srgbToLinear(x.g), srgbToLinear(x.b)); }
float linearToSrgb(float x) {
    return x <= 0.0031308 ? 12.92 * x : 1.055 * pow(x, 1.0 / 2.4) - 0.055;
}
vec3 linearToSrgb(vec3 x) { return vec3(linearToSrgb(x.r), linearToSrgb(x.g), linearToSrgb(x.b)); }

float smithG1(float x, float alpha2) {
    return 2.0 * x / (x + sqrt(alpha2 + (1.0 - alpha2) * x * x));
}

// f(wi, wo) max(n.wo, 0) with wi to the viewer and wo to the light, both above the plane.
vec3 evalCosine(vec3 n, vec3 wi, vec3 wo, vec3 diffuse, float roughness, vec3 specular) {
    vec3 h = normalize(wi + wo);
    float cosV = dot(n, wi), cosL = dot(n, wo), cosH = dot(n, h), cosVH = dot(wi, h);
    vec3 nxh = cross(n, h);
    float sin2H = dot(nxh, nxh);  // |n x h|^2: the GGX peak of smooth materials needs the precision
    if (wi.z <= 0.0 || wo.z <= 0.0 || cosV <= 0.0 || cosL <= 0.0) return vec3(0.0);
    float r = max(roughness, MIN_ROUGHNESS);
    float alpha2 = r * r * r * r;
    float d = alpha2 * cosH * cosH + sin2H;
    float ndf = alpha2 / (PI * d * d);
    vec3 fresnel = specular + (1.0 - specular) * pow(clamp(1.0 - cosVH, 0.0, 1.0), 5.0);
    vec3 value = vec3(0.0);
    if (useDiffuse == 1) value += diffuse / PI;
    if (useSpecular == 1) value += ndf * smithG1(cosL, alpha2) * smithG1(cosV, alpha2) * fresnel / (4.0 * cosL * cosV);
    return value * cosL;
}

// Radiance arriving from direction d (world, +z out of the sample), blurred for roughness r.
vec3 environmentRadiance(vec3 d, float r) {
    // Mitsuba's envmap frame: the map's +y is the world's +z (preview_envmap.xml rotates it so).
    vec3 local = vec3(d.x, d.z, -d.y);
    float u = atan(local.x, -local.z) / (2.0 * PI) + 0.5;
    // Half a texel from the band's edges: the bands of the other roughness levels lie beyond them.
    float halfTexel = 0.5 * environmentLevels / float(textureSize(environmentMap, 0).y);
    float v = clamp(acos(clamp(local.y, -1.0, 1.0)) / PI, halfTexel, 1.0 - halfTexel);
    float level = clamp(r, 0.0, 1.0) * (environmentLevels - 1.0);
    float low = floor(level);
    float high = min(low + 1.0, environmentLevels - 1.0);
    vec3 a = texture(environmentMap, vec2(u, (low + v) / environmentLevels)).rgb;
    vec3 b = texture(environmentMap, vec2(u, (high + v) / environmentLevels)).rgb;
    return mix(a, b, level - low);
}

vec3 environmentIrradiance(vec3 n) {
    vec3 local = vec3(n.x, n.z, -n.y);
    float x = local.x, y = local.y, z = local.z;
    return max(vec3(0.0),
        0.886227 * irradiance[0] + 1.023328 * (irradiance[1] * y + irradiance[2] * z + irradiance[3] * x)
        + 0.858086 * (irradiance[4] * x * y + irradiance[5] * y * z + irradiance[7] * x * z)
        + 0.247708 * irradiance[6] * (3.0 * z * z - 1.0) + 0.429043 * irradiance[8] * (x * x - y * y));
}

// Split-sum environment lighting (Karis 2013) with the analytic directional albedo of Karis 2014.
vec3 environmentShading(vec3 n, vec3 wi, vec3 diffuse, float roughness, vec3 specular) {
    vec3 color = vec3(0.0);
    if (useDiffuse == 1) color += diffuse / PI * environmentIrradiance(n);
    if (useSpecular == 1) {
        float cosV = clamp(dot(n, wi), 0.0, 1.0);
        vec4 c0 = vec4(-1.0, -0.0275, -0.572, 0.022), c1 = vec4(1.0, 0.0425, 1.04, -0.04);
        vec4 q = roughness * c0 + c1;
        float a004 = min(q.x * q.x, exp2(-9.28 * cosV)) * q.x + q.y;
        vec2 ab = vec2(-1.04, 1.04) * a004 + q.zw;
        color += environmentRadiance(reflect(-wi, n), roughness) * (specular * ab.x + ab.y);
    }
    return color;
}

void main() {
    // Pixel (row i, column j), row 0 at the top (+y): gl_FragCoord counts rows from the bottom.
    ivec2 texel = ivec2(int(gl_FragCoord.x), int(resolution.y) - 1 - int(gl_FragCoord.y));
    if (showHeight == 1) {  // the PNG's grey levels as they are stored
        fragColor = vec4(vec3(texelFetch(heightMap, texel, 0).r), 1.0);
        return;
    }
    vec3 p = vec3(-1.0 + 2.0 * gl_FragCoord.x / resolution.x, -1.0 + 2.0 * gl_FragCoord.y / resolution.y, 0.0) * extent;
    vec3 n = useNormalMap == 1 ? normalize(texelFetch(normalMap, texel, 0).rgb * 2.0 - 1.0) : vec3(0.0, 0.0, 1.0);
    vec3 diffuse = srgbToLinear(texelFetch(diffuseMap, texel, 0).rgb);
    float roughness = texelFetch(roughnessMap, texel, 0).r;
    vec3 specular = srgbToLinear(texelFetch(specularMap, texel, 0).rgb);
    vec3 wi = normalize(cameraPosition - p);
    vec3 radiance;
    if (environmentMode == 1) {
        radiance = environmentShading(n, wi, diffuse, roughness, specular);
    } else {
        vec3 toLight = lightPosition - p;
        radiance = evalCosine(n, wi, normalize(toLight), diffuse, roughness, specular) * intensity / dot(toLight, toLight);
    }
    fragColor = vec4(linearToSrgb(clamp(radiance, 0.0, 1.0)), 1.0);
}
