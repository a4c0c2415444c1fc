"""The benchmarks' description of the machine, which tells figures of different CPUs apart, and
their reports' files."""

import importlib.util
from pathlib import Path

_SPEC = importlib.util.spec_from_file_location("benchmarks_common",
                                               Path(__file__).resolve().parents[1] / "benchmarks" / "common.py")
common = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(common)

#: Two processors of /proc/cpuinfo, shortened; the second differs so that reading past the first shows.
CPUINFO = """processor\t: 0
vendor_id\t: AuthenticAMD
model name\t: AMD EPYC 7B12
cpu MHz\t\t: 2249.998
flags\t\t: fpu sse2 avx fma avx2 avx512f avx512_bf16 sha_ni

processor\t: 1
model name\t: Other CPU
cpu MHz\t\t: 1000.000
flags\t\t: fpu sse2
"""


def test_first_processor_is_described():
    description = common.cpu_description(CPUINFO)
    assert description == {"cpu_model": "AMD EPYC 7B12", "cpu_mhz": 2249.998,
                           "vector_extensions": ["avx2", "fma", "avx512f", "avx512_bf16"]}


def test_avx2_machine_lists_no_avx512():
    text = CPUINFO.replace(" avx512f avx512_bf16", "")
    assert common.cpu_description(text)["vector_extensions"] == ["avx2", "fma"]


def test_missing_cpuinfo_gives_empty_fields():
    assert common.cpu_description("") == {"cpu_model": None, "cpu_mhz": None, "vector_extensions": []}


def test_a_report_keeps_the_entries_other_benchmarks_wrote_into_its_file(tmp_path):
    import json

    path = tmp_path / "model_quality.json"
    common.write_report(path, "model_quality", {"rows": {"model": 1}})
    common.write_section(path, "detail", "detail", {"size": 1024})
    common.write_report(path, "model_quality", {"rows": {"model": 2}})
    document = json.loads(path.read_text())
    assert document["rows"] == {"model": 2} and document["detail"]["size"] == 1024
    assert not list(tmp_path.glob("*.tmp"))
