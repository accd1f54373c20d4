"""What the sequence commands share: the help of their common options, reading a sequence
and the run's settings, one-line errors, progress and the printed results."""

from __future__ import annotations

from pathlib import Path

from ._app import console, err_console, fail
from ._help import FACTS, formats_help, setting

__all__ = [
    "SIGMA_HELP",
    "ROBUST_HELP",
    "METHOD_HELP",
    "default_of",
    "help_of",
    "SEQUENCE_HELP",
    "INPUT_HELP",
    "format_options",
    "sequence_path",
    "load_sequence",
    "parse_sigmas",
    "OPTION_OF",
    "run_settings",
    "print_metrics",
    "check_out",
    "progress",
    "print_latency",
    "write_run_folder",
    "run_and_write",
    "print_result",
    "check_recording",
    "write_recording_file",
]


SIGMA_HELP = (
    "Override a sigma, NAME=VALUE, repeatable (e.g. inverse_box=3); NAME one of "
    f"{', '.join(FACTS['sigmas'])} (units in docs/sequences.md)."
)


ROBUST_HELP = (
    f"Robust kernel, repeatable: KERNEL ({', '.join(FACTS['robust_choices'])}) on box and "
    f"measured-ellipsoid factors (default auto: {FACTS['auto_box_kernel'][0]} with threshold "
    f"{FACTS['auto_box_kernel'][1]:g} when the detections are associated automatically, none with "
    "instance ids), or TYPE=KERNEL[:K] for one factor type "
    f"({', '.join(FACTS['robust_groups'])}; KERNEL one of {', '.join(FACTS['robust_kernels'])})."
)


METHOD_HELP = f"The back end: {', '.join(FACTS['methods'])}."


def default_of(name: str):
    """The default of a settings field (``RunSettings``, or ``online.NAME``: ``OnlineSettings``),
    as a command-line default (``help_of.FACTS``: read without importing ``mapping``)."""
    return setting(name)[0]


def help_of(name: str, prefix: str = "") -> str:
    """An option's help from the run's settings (``mapping.SETTINGS.help``, or the method
    overrides' ``SETTINGS.overrides``, as ``help_of.FACTS`` copies them), as a sentence."""
    text = setting(name)[1]
    return f"{prefix}: {text}." if prefix else f"{text[0].upper()}{text[1:]}."


#: The help of a SEQUENCE argument and of ``import``'s SOURCE: the registered formats, listed
#: once when the CLI is imported.
SEQUENCE_HELP = f"The sequence, in a registered format (docs/formats.md): {formats_help()}."


INPUT_HELP = f"The input, in a registered format (docs/formats.md): {formats_help()}."


def format_options(items) -> dict:
    """``--option NAME=VALUE`` items as keyword options of a format's reader (VALUE read as
    a YAML scalar: 3, 0.5, true, odometry)."""
    import yaml

    out = {}
    for item in items or []:
        name, sep, value = item.partition("=")
        name = name.strip().replace("-", "_")
        if not sep or not name.isidentifier():
            fail(f"--option: expected NAME=VALUE, got {item!r}")
        try:
            v = yaml.safe_load(value) if value.strip() else ""
        except yaml.YAMLError:
            v = value
        if isinstance(v, (list, dict)):
            v = value
        out[name] = v
    return out


def sequence_path(path: Path) -> None:
    """Refuse, before anything is read or written, a sequence path that is not there or
    cannot be resolved (a symbolic-link loop): one line, exit 2."""
    from ..io import SequenceFormatError, check_sequence_path

    try:
        check_sequence_path(path)
    except SequenceFormatError as e:
        fail(str(e))


def load_sequence(path: Path, options: dict | None = None):
    """The sequence at ``path`` in its registered format (``io.read_sequence``), with the
    format's keyword ``options``; errors as one line."""
    from ..io import SequenceFormatError, read_sequence

    try:
        seq = read_sequence(path, **(options or {}))
    except SequenceFormatError as e:
        fail(str(e))
    except ValueError as e:  # an option the format does not take, or a bad value
        fail(f"--option: {e}")
    return seq


def parse_sigmas(items) -> dict:
    """``--sigma NAME=VALUE`` items as {NAME: number} (the values are checked by
    ``RunSettings``)."""
    from ..mapping import SETTINGS

    out = {}
    for item in items or []:
        name, sep, value = item.partition("=")
        if not sep:
            fail(f"--sigma: expected NAME=VALUE with NAME one of {', '.join(sorted(SETTINGS.sigmas))}, got "
                f"{item!r}")
        try:
            out[name.strip()] = float(value)
        except ValueError:
            fail(f"--sigma: {value!r} is not a number (in {item!r})")
    return out


#: The command-line option of a settings field whose option is not ``--<field>``.
OPTION_OF = {"online.iterations": "--online-iterations", "online.warmup": "--warmup",
              "online": "--online"}


def run_settings(method: str, **options):
    """``RunSettings.of(method, **options)``: the run's settings, checked before anything is
    read; a bad one ends the command in one line naming its option."""
    from ..mapping import RunSettings, SettingsError

    try:
        return RunSettings.of(method, **options)
    except SettingsError as e:
        option = OPTION_OF.get(e.field, "--" + e.field.split(".")[-1].replace("_", "-"))
        fail(f"{option}: {e.reason}")


def print_metrics(metrics: dict) -> None:
    from ..evaluation import ate_line, shown

    s = metrics.get("summary")
    if s:
        console.print(
            f"mean IoU {shown(s['mean_iou'])}, orientation error {shown(s['mean_orientation_deg'], '.2f', '°')}, "
            f"centre error {shown(s['mean_center_error'], '.3f', ' m')} ({s['matched']}/{s['ground_truth_objects']} "
                f"objects)"
        )
    if "ate" in metrics:
        console.print(ate_line(metrics["ate"]))


def check_out(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        fail(f"--out: {out} exists and is not a folder")
    if out.exists() and any(out.iterdir()) and not overwrite:
        fail(f"--out: {out} exists and is not empty (use --overwrite)")


def progress(message: str) -> None:
    """The run's stages and LM iterations, on stderr (stdout keeps the results)."""
    err_console.print(f"[dim]{message}[/dim]", highlight=False)


def print_latency(records, rate) -> None:
    import numpy as np

    ms = 1e3 * np.array([r.seconds for r in records])
    console.print(f"online: {len(records)} frames, time per frame median {np.median(ms):.3g} ms, "
                  f"99th percentile {np.percentile(ms, 99):.3g} ms, max {ms.max():.3g} ms"
                  + (f" (frame period {1e3 / rate:.3g} ms)" if rate else ""))


def write_run_folder(out, seq, result, **options) -> dict:
    """``experiments.write_run``, its errors as one line."""
    from ..experiments import write_run

    try:
        return write_run(out, seq, result, **options)
    except FileExistsError as e:
        fail(f"--out: {e}")
    except OSError as e:  # the folder became unwritable, the disk is full, …
        fail(f"--out: cannot write {out}: {e.strerror or e}")


def run_and_write(seq, settings, out, overwrite, overlay, source=None):
    """Map ``seq`` with ``settings`` (``experiments.map_sequence``) and write the run's folder
    ``out`` (``experiments.write_outputs``); errors as one line."""
    from ..experiments import frame_rate, map_sequence

    check_out(out, overwrite)
    try:
        result, records = map_sequence(seq, settings, progress=progress)
    except ValueError as e:
        fail(f"{seq.name}: {e}")
    if records is not None:
        print_latency(records, frame_rate(seq))
    metrics = write_run_folder(out, seq, result, records=records, overlay=overlay, overwrite=overwrite, source=source)
    print_result(result, metrics.get("association"))
    print_metrics(metrics)
    console.print(f"wrote {out}")
    return result, metrics


def print_result(result, scores: dict | None = None) -> None:
    """The run's figures, its objects not mapped, and an automatic association's ``scores``
    (precision, recall: the metrics' ``association``) when given."""
    console.print(
        f"{result.method.name}: {len(result.objects)} objects, {result.iterations} iterations "
        f"({result.reason}), cost {result.initial_cost:.6g} -> {result.final_cost:.6g}"
    )
    for k, why in result.failed.items():
        err_console.print(f"object {k} not mapped: {why}")
    if result.association.get("mode") == "auto":
        said = (f": precision {scores['precision']:.3f}, recall {scores['recall']:.3f} against the instance ids"
                if scores and "precision" in scores else "")
        console.print(f"automatic data association, {len(result.objects) + len(result.failed)} tracks{said}")


def check_recording(path: Path, option: str) -> None:
    """Refuse, before anything is computed, a recording path that is a folder, and a
    missing rerun-sdk (the viewer extra)."""
    from ..experiments import RERUN_MISSING

    if path.is_dir():
        fail(f"{option}: {path} is a folder: expected the path of a .rrd file")
    try:
        import rerun  # noqa: F401
    except ImportError:
        fail(RERUN_MISSING)


def write_recording_file(path: Path, option: str, objects, trajectory, seq, to_groundtruth=None,
                     images: bool = True) -> None:
    """``experiments.write_recording`` (atomic), its errors as one line."""
    from ..experiments import write_recording

    try:
        write_recording(path, objects, trajectory, seq, to_groundtruth=to_groundtruth,
                        images=images)
    except ImportError as e:
        fail(str(e))
    except ValueError as e:
        fail(f"cannot record {path}: {e}")
    except OSError as e:
        fail(f"{option}: cannot write {path}: {e.strerror or e}")
    console.print(f"wrote {path} (open it with: rerun {path})")
