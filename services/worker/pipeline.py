"""The job pipeline behind the Celery tasks: analyze → search → render → (FBX) → finalize.

Each stage is idempotent and leaves nothing half-written:

- analyze: cached by the analysis code's version, the upload's sha256 and the style tempo
  range (the spec's, else the one the dataset's graph declares: ``style_tempo_range``; the bars
  count the octave that fits it) at ``analysis_key`` (the same song is analysed once per range
  and release, whoever asked); written atomically by the object store.
- search: adds the graph's learned music terms where it has learned models
  (``with_learned_terms``: they need the audio, which only the worker holds), then asks the
  graph store (``services.graphstore.client``: in-process in the embedded
  default, over HTTP in production); its answer is kept with the rendered files.
- render: writes into a private scratch folder ``job-<id>-<random>/`` and publishes it at
  ``jobs/<job_id>/`` (``ObjectStore.publish``: the files under a fresh version prefix, then
  ``jobs/<job_id>/manifest.json`` created last and only once); a published manifest means the
  render is complete, so a re-run skips it, and readers (the API) see only what it names.
- FBX: each ``alternatives/<k>.fbx`` is converted from a local copy of its BVH and added to the
  published result (``ObjectStore.publish_more``), file by file, so a restart skips done ones.
- finalize: the job row becomes ``succeeded`` with the alternatives and their costs (a
  conditional update: a cancelled or already-finished job is never overwritten).

Progress (stage, percent) goes to the job row as the stages pass.
"""

from __future__ import annotations

import json
import logging
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache, partial
from pathlib import Path

from dancegraph.errors import AudioError, DanceGraphError
from dancegraph.graph.search import SearchResult
from dancegraph.music.analysis import MusicAnalysis, analysis_version
from dancegraph.music.params import AnalysisParams
from dancegraph.spec import Spec, parse_spec
from dancegraph.store import ObjectStore
from services import jobs
from services.common.rigs import job_rig_output, write_rig_fbx
from services.config import Settings, get_settings
from services.config import object_store as settings_store
from services.db import session_scope
from services.graphstore.client import GraphStoreClient, single_library
from services.models import SUCCEEDED
from services.worker import state

log = logging.getLogger("dancegraph.worker")

# Stage names and the percent reached when each one starts (shown by GET /v1/jobs/{id}).
STAGES = {
    "analyze": 5.0,
    "search": 40.0,
    "render": 60.0,
    "fbx_queued": 80.0,
    "fbx": 82.0,
    "finalize": 98.0,
}
TIMELINE = "timeline.json"
SEARCH_FILE = "search.json"


def object_store(settings: Settings | None = None) -> ObjectStore:
    return settings_store(settings or get_settings())


def analysis_key(
    audio_sha256: str,
    tempo_range: tuple[float, float] | None = None,
    params: AnalysisParams | None = None,
) -> str:
    """Object-store key of the cached analysis of the song with this sha256:
    ``analysis/<version>/<sha256>.json``, or ``-<lo>-<hi>bpm.json`` for the analysis counted in
    a style tempo range, and ``-p<digest>`` before ``.json`` for a spec's analysis parameters
    other than the defaults; ``<version>`` is ``music.analysis.analysis_version()``, so analyses
    made by other analysis code or models are never read back."""
    folder = f"analysis/{analysis_version()}"
    name = audio_sha256
    if tempo_range is not None:
        lo, hi = tempo_range
        name += f"-{lo:g}-{hi:g}bpm"
    if params is not None and params != AnalysisParams():
        name += f"-p{params.digest()}"
    return f"{folder}/{name}.json"


# --- stages ---------------------------------------------------------------------------------


def analyze(
    store: ObjectStore,
    audio_key: str,
    audio_sha256: str,
    filename: str | None = None,
    tempo_range: tuple[float, float] | None = None,
    params: AnalysisParams | None = None,
) -> MusicAnalysis:
    """The song's analysis, computed once per sha256 and ``tempo_range`` (a dance style's (lo,
    hi) BPM: the bars count the octave that fits it, ``music.analysis.analyze``) and cached as
    ``MusicAnalysis.to_dict()``; always returned as read back from that JSON, so a first run and
    a re-run see the same numbers. An audio error names ``filename`` (the name the client
    uploaded), not the blob."""
    key = analysis_key(audio_sha256, tempo_range, params)
    if store.exists(key):
        data = json.loads(store.get_bytes(key))
    else:
        from dancegraph.music.analysis import analyze as analyze_music

        path = store.local_path(audio_key)
        try:
            data = analyze_music(str(path), tempo_range=tempo_range, params=params).to_dict()
        except AudioError as exc:
            if filename:
                exc.message = exc.message.replace(path.name, filename)
                exc.args = (exc.message,)
                exc.field = "audio"
            raise
        store.put_bytes(key, json.dumps(data).encode("utf-8"))
    return MusicAnalysis.from_dict(data)


def style_tempo_range(
    store: ObjectStore, spec: Spec, version: str | None = None
) -> tuple[float, float] | None:
    """The style tempo range whose octave the song's bars count (``render.style_tempo_range``:
    the spec's, else the one the dataset's graph carries: ``version``, default the current);
    without a graph only the spec's (the search stage names the missing graph)."""
    from dancegraph.render import style_tempo_range as for_graph

    try:
        graph = load_graph(store, single_library(spec), version)
    except DanceGraphError:
        graph = None
    return for_graph(spec, graph)


def with_learned_terms(
    store: ObjectStore,
    audio_key: str,
    analysis: MusicAnalysis,
    dataset: str,
    version: str | None = None,
) -> MusicAnalysis:
    """``analysis`` plus the music terms of the dataset's graph's (``version``, default the
    current) learned models (E_M
    style of the uploaded audio, rhythm top-3; ``embed.learned.add_music_terms``), so the search
    need not fall back to the descriptor bridge; ``analysis`` itself for a descriptor graph.
    Computed per job (about a second for a 3-min song), not cached: the cached analysis stays
    what the audio alone gives."""
    from dancegraph.embed.learned import add_music_terms

    try:
        graph = load_graph(store, dataset, version)
    except DanceGraphError:
        return analysis  # no such graph: the search stage names the problem
    return add_music_terms(analysis, graph, str(store.local_path(audio_key)))


def search(
    settings: Settings, spec: Spec, analysis: MusicAnalysis, version: str | None = None
) -> SearchResult:
    """Graph search of ``spec.dataset`` (``version``: the job's pinned one) through the
    graph-store client."""
    return graphstore_client(settings).search(analysis, spec, version)


def choose_dataset(store: ObjectStore, job, spec: Spec) -> tuple[Spec, dict | None]:
    """A spec naming a list of libraries or a ``style`` (``auto``: every library the tenant may
    use) on the one library ``graph.style_choice.resolve`` picks for the song (analysed at the
    spec's tempo range, else as tracked), and the choice with each candidate's scores, by the
    libraries' names; a spec naming one library, or a job that pinned one already, as it is."""
    from dancegraph.graph.style_choice import resolve
    from dancegraph.spec import parse_spec
    from services.common.libraries import candidates

    if job.dataset_graph or (isinstance(spec.dataset, str) and spec.style is None):
        return spec, None
    listed = spec.libraries() if isinstance(spec.dataset, list) else None
    with session_scope() as session:
        pins = candidates(session, store, job.tenant_id, listed)
    graphs = {name: load_graph(store, graph, version) for name, (graph, version) in pins.items()}
    rng = tuple(spec.tempo_range) if spec.tempo_range else None
    song = analyze(store, job.audio_key, job.audio_sha256, job.audio_filename, rng)  # type: ignore[arg-type]
    chosen, choice = resolve(spec, song, graphs)
    assert choice is not None  # a list or a style always chooses
    named = {g.name: name for name, g in graphs.items()}  # graph name → library name
    reason = choice["reason"]
    for graph, name in named.items():
        reason = reason.replace(graph, name)
    rows = [{**c, "name": named.get(c["name"], c["name"])} for c in choice["candidates"]]
    choice = {**choice, "chosen": named[choice["chosen"]], "reason": reason, "candidates": rows}
    return parse_spec(chosen, dataset=choice["chosen"]), choice


def pin_dataset(store: ObjectStore, job, spec: Spec) -> tuple[Spec, dict]:
    """The spec on the graph the job pinned when it started (``libraries.pin_job``: the
    tenant's newest built version of ``spec.dataset``, else the public library's current
    graph) and the timeline's ``library`` record (name, graph, graph_version)."""
    from services.common.libraries import pin_job

    with session_scope() as session:
        graph, version = pin_job(session, store, job, spec.libraries()[0])  # one, once chosen
    library = {"name": spec.dataset, "graph": graph, "graph_version": version}
    return spec.model_copy(update={"dataset": graph}), library


def graphstore_client(settings: Settings) -> GraphStoreClient:
    """LocalGraphStore (in-process) when ``graphstore_url`` is 'local', else HttpGraphStore."""
    return _graphstore_client(
        settings.graphstore_url, object_store(settings), settings.graphstore_memory_bytes
    )


@lru_cache(maxsize=4)
def _graphstore_client(url: str, store: ObjectStore, budget: int) -> GraphStoreClient:
    from services.graphstore.client import HttpGraphStore, LocalGraphStore

    if url == "local":
        return LocalGraphStore(store, budget)
    return HttpGraphStore(url)


def load_graph(store: ObjectStore, name: str, version: str | None = None):
    """A graph artifact of the dataset (default: its current version), memory-mapped, cached
    per process and version; render uses the version the search answered from."""
    from dancegraph.graph.artifact import current_version

    return _load_graph(store, name, version or current_version(store, name))


@lru_cache(maxsize=8)
def _load_graph(store: ObjectStore, name: str, version: str):
    from dancegraph.graph.artifact import graph_folder
    from dancegraph.graph.artifact import load_graph as load_artifact

    return load_artifact(graph_folder(store, name, version))


def render(
    store: ObjectStore,
    job_id: str,
    spec: Spec,
    analysis: MusicAnalysis,
    found: SearchResult,
    audio: dict[str, str] | None = None,
    on_rig=None,
    library: dict | None = None,
) -> list[str]:
    """Render BVH + timeline and publish them at ``jobs/<job_id>/``; returns the file names.

    ``audio``: the song's ``{file, sha256}`` for the timeline's provenance (what
    ``dancegraph preview`` finds the song by). FBX is not written here: it is the ``fbx``
    queue's work (a warm Blender per worker). ``on_rig``: the hook that also writes each
    alternative on the job's rig (``services.common.rigs.job_rig_output``). ``library``: the
    library the job pinned (``pin_dataset``), for the timeline's provenance.
    """
    if store.published(jobs.result_key(job_id)) is not None:
        return list_result_files(store, job_id)
    from dancegraph.render import render as render_motion

    here = ["bvh", *(["usd"] if "usd" in spec.output.formats else [])]  # FBX: the fbx queue's
    bvh_spec = spec.model_copy(update={"output": spec.output.model_copy(update={"formats": here})})
    graph = load_graph(store, single_library(spec), found.graph_version or None)
    tmp = store.temp_dir(f"job-{job_id}")
    try:
        extra = {k: v for k, v in (("audio", audio), ("library", library)) if v} or None
        render_motion(graph, analysis, found, bvh_spec, tmp, extra_provenance=extra, on_rig=on_rig)
        (tmp / SEARCH_FILE).write_text(json.dumps(found.to_dict()))
        # False: another worker published first; its complete result stands
        store.publish(jobs.result_key(job_id), tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return list_result_files(store, job_id)


def render_couple_result(
    store: ObjectStore,
    job_id: str,
    spec: Spec,
    analysis: MusicAnalysis,
    audio: dict[str, str] | None = None,
    rigs: dict | None = None,
) -> list[str]:
    """A couple job (``spec.couple``): the search on ``spec.dataset``'s couple graph in this
    process (``couple.graph.open_couple_graph``; the graph store serves solo graphs) and the
    render for two (``alternatives/<k>/lead.bvh``, ``follow.bvh`` and ``couple.glb``; FBX is
    the fbx queue's: ``fbx_sources``), published at ``jobs/<job_id>/``; returns the file
    names. ``rigs``: per partner the rig hook (``job_rig_output``; None: no rig), which writes
    ``alternatives/<k>/<partner>.rig.bvh|glb``.
    Raises NotFoundError(``couple_graph_missing``) where the library has no couple graph."""
    if store.published(jobs.result_key(job_id)) is not None:
        return list_result_files(store, job_id)
    from dancegraph.couple.graph import open_couple_graph
    from dancegraph.couple.render import render_couple
    from dancegraph.graph.search import search as search_graph

    graph = open_couple_graph(store, spec.libraries()[0])  # the pinned graph, once chosen
    found = search_graph(graph, analysis, spec)
    bvh_spec = spec.model_copy(
        update={"output": spec.output.model_copy(update={"formats": ["bvh"]})}
    )
    tmp = store.temp_dir(f"job-{job_id}")
    try:
        extra = {"audio": audio} if audio else None
        on_rig = {k: hook for k, hook in (rigs or {}).items() if hook is not None}
        render_couple(graph, analysis, found, bvh_spec, tmp, extra_provenance=extra, on_rig=on_rig)
        (tmp / SEARCH_FILE).write_text(json.dumps(found.to_dict()))
        store.publish(jobs.result_key(job_id), tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return list_result_files(store, job_id)


def list_result_files(store: ObjectStore, job_id: str) -> list[str]:
    """Names of a job's published result files, relative to ``jobs/<job_id>/``."""
    return sorted(jobs.result_files(store, job_id))


def fbx_sources(store: ObjectStore, job_id: str, *, rig: bool = False) -> list[str]:
    """The BVH files of a job the fbx queue converts: each alternative's ``<k>.bvh`` and a
    couple's ``<k>/lead.bvh``, ``<k>/follow.bvh`` (the library's skeleton), or with ``rig``
    the solo ``<k>.rig.bvh`` and a couple's ``<k>/lead.rig.bvh``, ``<k>/follow.rig.bvh``."""
    tail = ".rig.bvh" if rig else ".bvh"
    couple = [
        name
        for name in jobs.result_files(store, job_id)
        if name.startswith("alternatives/")
        and name.rsplit("/", 1)[-1] in (f"lead{tail}", f"follow{tail}")
        and name.split("/")[1].isdigit()
    ]
    return jobs.bvh_files(store, job_id, rig=rig) + sorted(couple)


def couple_glbs(store: ObjectStore, job_id: str) -> list[str]:
    """A couple job's ``alternatives/<k>/couple.glb`` files, which the fbx queue turns into
    one FBX of both dancers each (``couple.fbx``)."""
    names = jobs.result_files(store, job_id)
    return sorted(n for n in names if n.startswith("alternatives/") and n.endswith("/couple.glb"))


def fbx_name(name: str) -> str:
    """The FBX written beside the result file ``name`` (``<k>.bvh`` → ``<k>.fbx``,
    ``<k>.rig.bvh`` → ``<k>.rig.fbx``, ``<k>/couple.glb`` → ``<k>/couple.fbx``)."""
    return name.rsplit(".", 1)[0] + ".fbx"


def fbx_missing(store: ObjectStore, job_id: str) -> bool:
    """Whether some ``fbx_sources`` BVH or couple GLB of the job has no FBX beside it yet."""
    done = jobs.result_files(store, job_id)
    names = fbx_sources(store, job_id) + fbx_sources(store, job_id, rig=True)
    return not all(fbx_name(n) in done for n in names + couple_glbs(store, job_id))


def _couple_fbx_writer(store: ObjectStore, job_id: str, glb_name: str):
    """The writer of ``<k>/couple.fbx`` from ``glb_name``: both dancers at the rate and frame
    count of the alternative's ``lead.bvh``."""
    from dancegraph.motion.bvh import read_bvh
    from services.worker import fbx_export

    def write(glb: Path, out: Path) -> None:
        lead_name = glb_name.rsplit("/", 1)[0] + "/lead.bvh"
        lead = read_bvh(_result_file(store, published_result(store, job_id), lead_name))
        fbx_export.export_glb(glb, out, fps=lead.fps, frames=lead.n_frames)

    return write


def export_fbx(store: ObjectStore, job_id: str, fps: float, on_file=None, on_rig=None) -> list[str]:
    """Add an FBX beside each ``fbx_sources`` BVH (``alternatives/<k>.fbx``, a couple's
    ``<k>/lead.fbx`` and ``<k>/follow.fbx``) and each couple GLB (``<k>/couple.fbx``, both
    dancers; skipping ones already there), and with ``on_rig(name, bvh, fbx)`` (``name``: the
    result's ``<k>.rig.bvh`` or ``<k>/<partner>.rig.bvh``) each ``.rig.fbx`` beside it. Raises
    DanceGraphError ``result_missing`` when the published result leaves the store meanwhile."""
    from services.worker import fbx_export

    prefix = jobs.result_key(job_id)
    todo: list[tuple[str, Callable[[Path, Path], object] | None]]
    todo = [(name, None) for name in fbx_sources(store, job_id)]
    todo += [(name, _couple_fbx_writer(store, job_id, name)) for name in couple_glbs(store, job_id)]
    if on_rig is not None:
        todo += [(name, partial(on_rig, name)) for name in fbx_sources(store, job_id, rig=True)]
    for i, (name, writer) in enumerate(todo):
        files = published_result(store, job_id)
        target = fbx_name(name)
        if target in files:
            continue
        tmp = store.temp_dir(f"fbx-{job_id}")
        try:
            out = tmp / target.rsplit("/", 1)[1]
            source = _result_file(store, files, name)
            if writer is None:
                fbx_export.export(source, out, fps=fps)
            else:
                writer(source, out)
            try:
                store.publish_more(prefix, {target: out})
            except FileNotFoundError as exc:  # the manifest went during the export
                raise _result_missing() from exc
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        if on_file is not None:
            on_file(i)
    return list_result_files(store, job_id)


def wants_fbx(spec: Spec) -> bool:
    return "fbx" in spec.output.formats


def published_result(store: ObjectStore, job_id: str) -> dict[str, str]:
    """The job's published result files (``jobs.result_files``); raises DanceGraphError
    ``result_missing`` when the store no longer holds them (emptied or lost under the job),
    so the job fails with that name instead of an internal error."""
    files = jobs.result_files(store, job_id)
    if SEARCH_FILE not in files:
        raise _result_missing()
    return files


def _result_file(store: ObjectStore, files: dict[str, str], name: str) -> Path:
    """A local copy of the published result file ``name``; ``result_missing`` when it is gone."""
    try:
        return store.local_path(files[name])
    except (KeyError, FileNotFoundError) as exc:
        raise _result_missing() from exc


def _result_missing() -> DanceGraphError:
    return DanceGraphError(
        "the job's rendered result is no longer in the object store (removed while the job ran);"
        " submit the song again",
        code="result_missing",
    )


def finalize(store: ObjectStore, job_id: str) -> bool:
    """Mark the job succeeded with its alternatives, costs and files; False if already final.
    Raises DanceGraphError ``result_missing`` when the result left the store."""
    files = published_result(store, job_id)
    try:
        found = json.loads(store.get_bytes(files[SEARCH_FILE]))
    except FileNotFoundError as exc:
        raise _result_missing() from exc
    result = dict(found)
    result["files"] = sorted(f for f in files if f != SEARCH_FILE)
    with session_scope() as session:
        ok = jobs.set_status(
            session, job_id, SUCCEEDED, stage="done", progress=100.0, result=result
        )
    if ok:
        log.info("job succeeded", extra={"job_id": job_id, "files": len(result["files"])})
    return ok


def fail(job_id: str, exc: DanceGraphError) -> bool:
    """A named failure (the error's stable code) — the user's input, not the machine, is at fault."""
    with session_scope() as session:
        return jobs.fail_job(session, job_id, exc.code, exc.message, exc.field)


@dataclass
class RunOutcome:
    """What ``run_job`` did: 'skipped' (not ours / final), 'succeeded', 'fbx_queued'."""

    status: str
    files: list[str] | None = None


def run_job(job_id: str, settings: Settings | None = None) -> RunOutcome:
    """Claim and run the analysis-queue part of a job (raises on failure; the task decides)."""
    settings = settings or get_settings()
    store = object_store(settings)
    job = state.claim(job_id, stale_after_s=settings.job_timeout_s)
    if job is None:
        log.info("not claimed (final, or held by a live worker)", extra={"job_id": job_id})
        return RunOutcome("skipped")
    spec = parse_spec(job.spec)  # the task's entry: parsed once, passed on as the model
    interval = state.heartbeat_interval(settings.job_timeout_s)
    with state.Heartbeat(job_id, interval) as beat:
        state.progress(job_id, "analyze", STAGES["analyze"])
        spec, choice = choose_dataset(store, job, spec)
        spec, library = pin_dataset(store, job, spec)
        if choice is not None:
            library["choice"] = choice
        tempo_range = style_tempo_range(store, spec, library["graph_version"])
        analysis = analyze(
            store, job.audio_key, job.audio_sha256, job.audio_filename, tempo_range,
            spec.analysis_params(),
        )  # fmt: skip
        beat.check()
        with session_scope() as session:
            _set_summary(session, job_id, analysis)
        state.progress(job_id, "search", STAGES["search"])
        if spec.couple:  # the couple's own graph, searched and rendered here
            source = {"file": job.audio_filename, "sha256": job.audio_sha256}
            rigs = {
                partner: job_rig_output(store, settings.database_url, job.tenant_id, rig_id)
                for partner, rig_id in (
                    ("lead", spec.output.rig),
                    ("follow", spec.output.follow_rig),
                )
            }
            files = render_couple_result(store, job_id, spec, analysis, source, rigs)
            if wants_fbx(spec) and fbx_missing(store, job_id):
                state.progress(job_id, "fbx_queued", STAGES["fbx_queued"])
                return RunOutcome("fbx_queued", files)
            state.progress(job_id, "finalize", STAGES["finalize"])
            finalize(store, job_id)
            return RunOutcome("succeeded", files)
        version = library["graph_version"]
        terms = with_learned_terms(store, job.audio_key, analysis, library["graph"], version)
        found = search(settings, spec, terms, version)
        beat.check()
        state.progress(job_id, "render", STAGES["render"])
        source = {"file": job.audio_filename, "sha256": job.audio_sha256}
        on_rig = job_rig_output(
            store,
            settings.database_url,
            job.tenant_id,
            spec.output.rig,
            ("bvh", "glb", *(("usd",) if "usd" in spec.output.formats else ())),
        )
        files = render(store, job_id, spec, analysis, found, source, on_rig, library)
        beat.check()
        if wants_fbx(spec) and fbx_missing(store, job_id):
            state.progress(job_id, "fbx_queued", STAGES["fbx_queued"])
            return RunOutcome("fbx_queued", files)
        state.progress(job_id, "finalize", STAGES["finalize"])
    finalize(store, job_id)
    return RunOutcome("succeeded", files)


def run_fbx(job_id: str, settings: Settings | None = None) -> RunOutcome:
    """Claim the FBX stage of a job (handed over by ``run_job``), export, finalize."""
    settings = settings or get_settings()
    store = object_store(settings)
    job = state.claim(job_id, stale_after_s=settings.job_timeout_s, stages=("fbx_queued",))
    if job is None:
        return RunOutcome("skipped")
    interval = state.heartbeat_interval(settings.job_timeout_s)
    with state.Heartbeat(job_id, interval) as beat:
        state.progress(job_id, "fbx", STAGES["fbx"])
        n = len(fbx_sources(store, job_id)) + len(fbx_sources(store, job_id, rig=True))
        n = max(1, n + len(couple_glbs(store, job_id)))
        span = STAGES["finalize"] - STAGES["fbx"]

        def on_file(i: int) -> None:
            beat.check()
            state.progress(job_id, "fbx", STAGES["fbx"] + span * (i + 1) / n)

        spec = parse_spec(job.spec)
        rigs = {"lead": spec.output.rig, "follow": spec.output.follow_rig}
        rig_ids = {partner: rig_id for partner, rig_id in rigs.items() if rig_id is not None}

        def on_rig(name: str, bvh: Path, fbx: Path) -> None:  # the follow's rig for its files
            rig_id = rig_ids["follow" if name.endswith("/follow.rig.bvh") else "lead"]
            write_rig_fbx(store, settings.database_url, job.tenant_id, rig_id, bvh, fbx)

        files = export_fbx(store, job_id, float(spec.output.fps), on_file, on_rig)
        state.progress(job_id, "finalize", STAGES["finalize"])
    finalize(store, job_id)
    return RunOutcome("succeeded", files)


def _set_summary(session, job_id: str, analysis: MusicAnalysis) -> None:
    from sqlalchemy import update

    from services.models import Job

    session.execute(
        update(Job)
        .where(Job.id == job_id)
        .values(analysis_summary=analysis.summary())
        .execution_options(synchronize_session=False)
    )
