# Configuration and sample-sheet validation: an invalid config or sheet fails
# here, before any job runs, with a message naming the key or the row; then the
# functions that the .smk files call for inputs and params, kept apart from the
# rules (snakemake --lint). Calibration's own are in calibrate_common.smk.

import csv
import json
from pathlib import Path

import yaml
from snakemake.exceptions import WorkflowError
from snakemake.utils import validate

from facetsynth.io.errors import excerpt
from facetsynth.io.pages import memory_defaults

memory_defaults()  # every job's numpy on small pages, its freed memory reused (src/facetsynth/io/pages.py)


def scalars(value):
    """Config leaves that --config passes as strings (it parses with YAML's BaseLoader: 'scatter={tiles: 8}'
    gives {'tiles': '8'}) read as YAML scalars: a leaf whose YAML is a number, a boolean or null becomes
    one; any other string (a path, a name, 'auto') is left as given, and validation names a bad one."""
    if isinstance(value, list):
        return [scalars(v) for v in value]
    if isinstance(value, dict):
        return {k: scalars(v) for k, v in value.items()}
    if isinstance(value, str):
        try:
            parsed = yaml.safe_load(value)
        except yaml.YAMLError:
            return value
        return parsed if parsed is None or isinstance(parsed, (bool, int, float)) else value
    return value


def apply_preset(config):
    """Fill every knob the chosen preset sets (config key 'preset', one of the names under 'presets')
    that its section leaves out; a knob given in its section (config file, --configfile, --config)
    overrides the preset. Returns the knobs set by the preset as {"section.knob": value}."""
    presets = config.get("presets") if isinstance(config.get("presets"), dict) else {}
    name = config.get("preset", "balanced")
    if not isinstance(name, str) or name not in presets:
        raise WorkflowError(
            f"config: unknown preset {name!r} (config key 'preset'); "
            f"choose one of: {', '.join(map(str, presets)) or 'none defined under presets'}"
        )
    filled = {}
    chosen = presets[name] if isinstance(presets[name], dict) else {}  # else validation names it
    for section, knobs in chosen.items():
        if not isinstance(knobs, dict):
            continue
        if config.get(section) is None:  # a section all of whose knobs come from the preset
            config[section] = {}
        target = config[section]
        if not isinstance(target, dict):
            continue  # validation below names the bad section
        for knob, value in knobs.items():
            if knob not in target:
                target[knob] = value
                filled[f"{section}.{knob}"] = value
    return filled


MAX_SCATTER_TILES = 1024
"""scatter.tiles at most: the DAG grows by 3 jobs per tile and sample, and building it takes ~13 ms a tile
(measured, one sample: 1 tile 3.4 s, 256 8.4 s, 1024 16 s, 2048 29 s, 4096 66 s; 100000 never finished).
1024 jobs per stage already split the paper's scale (800 x 800 points: 2500 tiles of 256) into parts of
2 to 3 tiles: beyond it, parts are empty or hold one tile (docs/decisions.md, issue 32)."""


def cross_check(config):
    """Knobs that each pass the schema but contradict each other: a WorkflowError naming both keys, before
    any job runs (each would otherwise fail, or silently misbehave, in the stage that reads them, after
    every stage before it has run)."""

    def fail(problem):
        raise WorkflowError(f"config: {problem}")

    params = config["params"]
    if not params["eta_min"] < params["eta_max"]:
        fail(
            f"params.eta_min ({params['eta_min']}) must be less than params.eta_max ({params['eta_max']}): "
            "the bounds of eta's fit contradict"
        )
    if not params["eta_min"] <= params["eta_default"] <= params["eta_max"]:
        fail(
            f"params.eta_default ({params['eta_default']}) lies outside [params.eta_min, params.eta_max] = "
            f"[{params['eta_min']}, {params['eta_max']}]: the default eta must be one the fit could reach"
        )
    cluster = config["cluster"]
    if not cluster["min_representatives"] <= cluster["max_representatives"]:
        fail(
            f"cluster.min_representatives ({cluster['min_representatives']}) exceeds cluster.max_representatives "
            f"({cluster['max_representatives']}): the range of k scanned is empty"
        )
    ranges = [
        ("resample.n_theta_range", config["resample"]["n_theta_range"]),
        ("synthesize.overlap", config["synthesize"]["overlap"]),
    ]
    ranges += [
        (f"presets.{name}.resample.n_theta_range", preset["resample"]["n_theta_range"])
        for name, preset in config["presets"].items()
    ]
    for key, (low, high) in ranges:
        if not low <= high:
            fail(f"{key} is [{low}, {high}]: its minimum exceeds its maximum")
    names = [view["name"] for view in config["validate"]["views"]]
    twice = sorted({name for name in names if names.count(name) > 1})
    if twice:
        fail(
            f"validate.views: the name {twice[0]!r} is given to {names.count(twice[0])} views: each view's "
            "outputs are named after it"
        )
    tiles = config["scatter"]["tiles"]
    if tiles > MAX_SCATTER_TILES:
        fail(
            f"scatter.tiles is {tiles}, more than {MAX_SCATTER_TILES} jobs per stage and sample: the job graph "
            f"alone would take minutes to hours to build, and every part beyond the capture's tiles of "
            f"{256} points is empty; use at most {MAX_SCATTER_TILES}"
        )


config.update(scalars(config))
PRESET_KNOBS = apply_preset(config)
validate(config, "../schemas/config.schema.yaml")
cross_check(config)
SCATTER_TILES = config["scatter"]["tiles"]


scattergather:
    tiles=SCATTER_TILES,


# resample, partial_ndf and baseline_ward: at scatter.tiles 1 one job runs the whole stage; above it, part jobs
# of whole tiles (`use rule STAGE as STAGE_part`) and the stage's rule joins them (docs/decisions.md, "On a cluster")
SCATTERED = SCATTER_TILES > 1


def scatter_parts(**patterns):
    """The part files a scattered stage's join reads, by input name (patterns with {{sample}} and {scatteritem});
    none at scatter.tiles 1, where the stage's rule runs it whole."""
    return {name: gather.tiles(pattern) for name, pattern in patterns.items()} if SCATTERED else {}


def read_samples(path):
    """The sample sheet as {sample: row}, each row validated against the schema."""
    if not Path(path).is_file():
        raise WorkflowError(f"{path}: sample sheet not found (config key 'samples')")
    try:
        with open(path, newline="") as f:
            reader = csv.DictReader(f, delimiter="\t")
            rows = [(reader.line_num, row) for row in reader]
            header = reader.fieldnames or []
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise WorkflowError(f"{path}: not a readable sample sheet (config key 'samples'): {excerpt(e)}")
    twice = sorted({name for name in header if header.count(name) > 1})
    if twice:
        raise WorkflowError(f"{path} line 1: the column '{excerpt(twice[0])}' is named twice in the header")
    samples = {}
    for line, row in rows:
        extra = [v for v in row.get(None) or [] if v != ""]
        if extra:
            raise WorkflowError(
                f"{path} line {line}: {len(extra)} field(s) beyond the header's {len(header)} "
                f"columns ({', '.join(map(str, header))}), the first '{excerpt(extra[0], 40)}': "
                "a tab too many, or a column missing from the header?"
            )
        row = {k: v for k, v in row.items() if k is not None and v not in (None, "")}
        try:
            validate(row, "../schemas/samples.schema.yaml")
        except WorkflowError as e:
            raise WorkflowError(f"{path} line {line}: {e}")
        if row["sample"] in samples:
            raise WorkflowError(f"{path} line {line}: sample '{row['sample']}' appears twice")
        if not Path(row["path"]).exists():
            raise WorkflowError(f"{path} line {line}: path '{row['path']}' of sample '{row['sample']}' does not exist")
        if row["source"] != "import" and Path(row["path"]).is_dir():
            raise WorkflowError(
                f"{path} line {line}: path '{row['path']}' of sample '{row['sample']}' is a folder; "
                f"a {row['source']} sample's path is a file"
            )
        if "rig" in row and Path(row["rig"]).is_dir():
            raise WorkflowError(
                f"{path} line {line}: rig '{row['rig']}' of sample '{row['sample']}' is a folder, "
                "not a rig description file"
            )
        samples[row["sample"]] = row
    if not samples:
        raise WorkflowError(f"{path}: the sample sheet lists no samples")
    for name, row in samples.items():
        main = row.get("rotation_of")
        if main is not None and (main not in samples or "rotation_of" in samples[main]):
            raise WorkflowError(
                f"{path}: sample '{name}' is a rotation of '{main}', which is not a sample of its own in the sheet"
            )
        if "rotation_deg" in row and row["source"] != "virtual":
            raise WorkflowError(
                f"{path}: sample '{name}': rotation_deg applies to virtual samples only (a real "
                "capture is turned on the rig)"
            )
    return samples


SAMPLE_SHEET = read_samples(config["samples"])
SAMPLES = list(SAMPLE_SHEET)
MODEL_SAMPLES = [s for s in SAMPLES if "rotation_of" not in SAMPLE_SHEET[s]]  # rotations only feed synthesis


def rotations_of(sample):
    """The samples of the sheet that are further rotations of ``sample`` (paper 002 sec. 4)."""
    return [s for s in SAMPLES if SAMPLE_SHEET[s].get("rotation_of") == sample]


wildcard_constraints:
    sample="|".join(SAMPLES),


def sample_rig(sample):
    """Rig description of a virtual sample."""
    return SAMPLE_SHEET[sample].get("rig", config["virtual"]["rig"])


def rendered_truth(sample):
    """{"scene", "rig"} the virtual rig renders a sample's held-out truth from: a virtual sample's, or a rig
    sample's whose camera backend is the virtual one (a rehearsal of the real rig); None for any other."""
    row = SAMPLE_SHEET[sample]
    if row["source"] == "virtual":
        return {"scene": row["path"], "rig": sample_rig(sample)}
    if row["source"] == "rig":
        try:
            camera = yaml.safe_load(Path(row["path"]).read_text())["camera"]
        except (OSError, yaml.YAMLError, KeyError, TypeError):
            return None  # the capture job names the problem
        if isinstance(camera, dict) and camera.get("backend") == "virtual" and "scene" in camera and "rig" in camera:
            return {"scene": camera["scene"], "rig": camera["rig"]}
    return None


def source_files(row):
    """The files a sample's capture is made from, beyond its sheet path, as inputs of the capture rule; editing
    one re-runs the chain from capture (Snakemake compares modification times). An import: its manifest and
    every exposure file the manifest lists; a virtual scene: the measured BRDF files its regions name. A
    manifest or scene that cannot be read yields what could be listed: the capture job then names the problem."""
    path = Path(row["path"])
    if row["source"] == "lp":
        try:
            from facetsynth.rti import lp

            listed = [path.parent / name for name in lp.read(path)[0]] + [lp.side_file(path)]
        except Exception:  # the capture job names the problem
            listed = []
        return [str(path)] + [str(f) for f in listed if f.is_file()]
    if row["source"] == "import":
        manifest = path / "manifest.json" if path.is_dir() else path
        try:
            frames = json.loads(manifest.read_text())["frames"]
            listed = [manifest.parent / e["file"] for f in frames for e in f["exposures"]]
        except (OSError, ValueError, KeyError, TypeError):
            listed = []
        return [str(manifest)] + [str(f) for f in listed if f.is_file()]
    if row["source"] == "virtual":
        try:
            regions = yaml.safe_load(path.read_text())["regions"]
            listed = [path.parent / r["measured"]["file"] for r in regions if "measured" in r]
        except (OSError, yaml.YAMLError, KeyError, TypeError):
            listed = []
        return [str(f) for f in listed if f.is_file()]
    return [rig_calibration(row)]


def rig_calibration(row):
    """The calibration file a real rig's description names (built by rule calibrate when it is one of its
    outputs); the description itself when it cannot be read: the capture job then names the problem."""
    try:
        return str(yaml.safe_load(Path(row["path"]).read_text())["calibration"])
    except (OSError, yaml.YAMLError, KeyError, TypeError):
        return row["path"]


def final_outputs(sample):
    """What a user takes away: the fitted SVBRDF with its stencil models and self-check, and for a sample whose
    held-out views the virtual rig can render (a virtual one, or the rig with the virtual camera)
    the held-out validation; a virtual sample's rectified frames scored against its truth."""
    # every sample: the fit against its own frames
    outputs = [
        f"results/{sample}/svbrdf",
        f"results/{sample}/stencil_fit/metrics.json",
        f"results/{sample}/selfcheck/metrics.json",
    ]
    if rendered_truth(sample) is not None:
        outputs.append(f"results/{sample}/validate/metrics.json")
    if SAMPLE_SHEET[sample]["source"] == "virtual":  # its truth: scored beside the fit (issue 31)
        outputs += [f"results/{sample}/truth/rectify.json", f"results/{sample}/truth/refine.json"]
    outputs.append(f"results/{sample}/export/metrics.json")  # the portable glTF material and its loss
    outputs += report_figures(sample)  # the figures of `snakemake --report` (workflow/rules/report.smk)
    return outputs


def report_figures(sample):
    """The report figures of ``sample`` (targets of the default run); the benchmark plots with the first
    sample's."""
    out = [
        f"results/{sample}/report/{name}.png" for name in ("capture", "relief", "kd", "ks", "eta", "ndf", "clusters")
    ]
    out.append(f"results/{sample}/report/stencil")
    if rendered_truth(sample) is not None:
        out += [f"results/{sample}/report/heldout_{view}.png" for view in HELDOUT_VIEWS]
    if sample == MODEL_SAMPLES[0]:
        out += [f"results/report/bench/{name}.png" for name in BENCH_FIGURES]
    return out


def rotation_inputs(wildcards):
    """The geometry and partial NDF tables of the sample's further rotations (sec. 4)."""
    rotations = rotations_of(wildcards.sample)
    return {
        "rotation_geometry": [f"results/{r}/separate/geometry.json" for r in rotations],
        "rotation_ndf": [f"results/{r}/partial_ndf/ndf" for r in rotations],
    }


def capture_inputs(wildcards):
    """The capture rule's inputs: the sheet path, the files the capture is made from (source_files) and, for a
    virtual sample, its rig description."""
    row = SAMPLE_SHEET[wildcards.sample]
    inputs = {"path": row["path"], "sources": source_files(row)}
    if row["source"] == "virtual":
        inputs["rig"] = sample_rig(wildcards.sample)
    return inputs


def virtual_scene(wildcards):
    """The scene and rig the held-out views of a sample are rendered from (heldout_capture's inputs, validate's
    rig); a WorkflowError for a sample the virtual rig cannot render."""
    truth = rendered_truth(wildcards.sample)
    if truth is None:
        raise WorkflowError(
            f"validate: sample '{wildcards.sample}' is not virtual, so there is no held-out "
            "ground truth to render; validate against a held-out capture of your own with "
            "`facetsynth predict results/SAMPLE/svbrdf HELDOUT/manifest.json OUT` (README)"
        )
    return truth


def export_inputs(wildcards):
    """The glTF export's inputs: the SVBRDF and, for a sample with rendered held-out truth, the held-out views,
    the full SVBRDF's validation metrics and the truth's rig (HELDOUT_VIEWS: validate.smk)."""
    inputs = {"svbrdf": f"results/{wildcards.sample}/svbrdf"}
    truth = rendered_truth(wildcards.sample)
    if truth is not None:
        inputs["heldout"] = [f"results/{wildcards.sample}/validate/heldout/{view}" for view in HELDOUT_VIEWS]
        inputs["validate_metrics"] = f"results/{wildcards.sample}/validate/metrics.json"
        inputs["rig"] = truth["rig"]
    return inputs
