"""RELIGHT_OT_relight_strip: relight a footage strip and add the result as a new strip.

Each lighting is a take: a folder of the strip's (v001, v002, ...: addon/takes.py) and a strip
named after it ("Shot relit v002"), so changing the light and relighting keeps the earlier take
beside the new one; the same lighting again resumes its take. The frames in a take are named like
the source's (shot.1001.exr -> relit.1001.exr; a movie's by scene frame).

In the UI the pipeline runs on a worker thread driven by a modal timer (progress bar, ESC cancels);
under ``bpy.app.background`` timers never fire, so the same pipeline runs synchronously and prints
its progress. The worker touches no Blender data: everything it needs is gathered beforehand."""

from __future__ import annotations

import pathlib
import threading
import time
import traceback

import bpy
import numpy as np

from ..addon.errors import Cancelled, InputError, LightingError, RelightError
from . import bridge, preview_light

RELIT_SUFFIX = " relit"
MATTE_SUFFIX = " matte"

# The exception that ended the last synchronous run (execute), None after a run that finished:
# for scripts that need its kind, not only the reported text (the batch run, ops/batch.py,
# turns it into its exit status and, with --debug, shows its traceback).
last_error = None
# The addon.pipeline.RunResult of the last synchronous run that finished (its out_dir is the
# take's folder) and the numbered names its frames were published under (relit.1001.exr, ...).
last_result = None
last_published = []

# The interactive run going on (one at a time: a second would fight the first for the CPU and,
# on the same strip, for its output folder), or None.
running = None

# Where a synchronous run (execute) sends its progress (done, total, text) and log lines; None
# prints them. The batch run's --progress json (ops/batch.py) sets its own.
progress_sink = None
log_sink = None


def schedule_lights(context, job: bridge.Job):
    """(lights, warnings): the target light of every visible frame of the strip, or one light
    when the lighting is static. Always the whole strip, even for a farm chunk: the pipeline
    indexes lights by clip frame, and every chunk must describe the same run. LightingError
    saying what to set in the scene when the light is black on every frame (the pipeline
    refuses it too, in words that know nothing of scenes)."""
    from ..addon import pipeline
    from . import scene_light

    frames = range(job.frame_start, job.frame_start + job.frame_count)
    schedule = scene_light.light_schedule(context.scene, frames, **job.light_args)
    lights = np.asarray(schedule.lights, dtype=np.float32)
    if all(pipeline.black_lights(lights, job.model.contract)):
        raise LightingError(schedule.black_message)
    return lights, list(schedule.warnings)


def run_pipeline(job: bridge.Job, lights, on_progress=None, should_cancel=None, log=None):
    """The Blender-free part of a run (safe on a worker thread)."""
    from ..addon import pipeline

    return pipeline.relight_clip(job.clip, lights, job.out_dir, job.options,
                                 frames=list(job.clip_frames), on_progress=on_progress,
                                 should_cancel=should_cancel, log=log)


def add_image_strip(scene, name: str, files: list[pathlib.Path], channel: int, frame_start: int,
                    colorspace: str):
    strips = scene.sequence_editor.strips
    old = strips.get(name)
    if old is not None:  # a re-run replaces its own strip instead of stacking copies
        strips.remove(old)
    channel = bridge.free_channel(strips, channel, frame_start, frame_start + len(files))
    strip = strips.new_image(name, str(files[0]), channel, frame_start)
    for path in files[1:]:
        strip.elements.append(path.name)
    strip.colorspace_settings.name = colorspace
    return strip


def publish_numbered(job: bridge.Job, result) -> list[str]:
    """This run's finished frames under the source's frame numbers in its take folder (hard
    links to the pipeline's files: addon/numbered.py); the relit names, in frame order."""
    from ..addon import numbered

    return numbered.publish_frames(result.out_dir, job.clip_frames, job.numbers, job.digits,
                                   matte=job.options.write_matte)


def take_label(result) -> str:
    """'v002': the take a run wrote into."""
    return pathlib.Path(result.out_dir).name


def add_result_strips(context, job: bridge.Job, result) -> list:
    """The take's relit strip above the source (and its matte above that), with the source's
    timing. Only a take that has every visible frame gets strips; a farm chunk just writes
    frames."""
    from ..addon import numbered

    take = pathlib.Path(result.out_dir)

    def files(prefix):
        return [take / numbered.numbered_name(prefix, job.numbers[i], job.digits)
                for i in range(job.frame_count)]

    relit = files("relit")
    if not all(p.is_file() for p in relit):
        return []
    scene = context.scene
    label = take_label(result)
    added = [add_image_strip(scene, f"{job.strip_name}{RELIT_SUFFIX} {label}", relit,
                             job.channel + 1, job.frame_start, bridge.LINEAR)]
    if job.options.write_matte:
        matte = files("matte")
        if all(p.is_file() for p in matte):
            strip = add_image_strip(scene, f"{job.strip_name}{MATTE_SUFFIX} {label}", matte,
                                    added[0].channel + 1, job.frame_start, "Non-Color")
            strip.mute = True  # an opaque matte above would hide the relit strip
            added.append(strip)
    return added


def show_source_light(result) -> None:
    """Preview the mean source light the network estimated (saved by the pipeline as .npy)."""
    files = sorted((pathlib.Path(result.out_dir) / "source_light").glob("*.npy"))
    if files:
        lights = [np.load(f) for f in files[:64]]
        preview_light.set_preview(preview_light.SOURCE_IMAGE, np.mean(lights, axis=0))


def poll_run(operator, context, need_strip: bool) -> bool:
    """Whether a relight may start now, with the reason set as the poll message where not: one
    run at a time, and (``need_strip``) an active footage strip to run on."""
    if context.scene is None:
        return False
    reason = None
    if running is not None:
        reason = f"Relighting '{running}' is under way; wait for it, or press Esc to cancel it"
    elif need_strip:
        editor = context.scene.sequence_editor
        strip = editor.active_strip if editor else None
        if strip is None or strip.type not in bridge.FOOTAGE_TYPES:
            reason = "Select a footage strip (a movie or an image sequence)"
    if reason:
        operator.poll_message_set(reason)
    return reason is None


class RELIGHT_OT_relight_strip(bpy.types.Operator):
    """Relight the active footage strip under the chosen lighting; adds a relit EXR strip above"""
    bl_idname = "relight.relight_strip"
    bl_label = "Relight Strip"
    bl_options = {'REGISTER', 'UNDO'}

    strip: bpy.props.StringProperty(name="Strip", options={'SKIP_SAVE'},
                                    description="Strip to relight; empty uses the active strip")
    models_dir: bpy.props.StringProperty(name="Models Folder", options={'SKIP_SAVE', 'HIDDEN'},
                                         description="Overrides the preferences' models folder")
    show_traceback: bpy.props.BoolProperty(
        name="Show Traceback", default=True, options={'SKIP_SAVE', 'HIDDEN'},
        description="Print an unexpected error's traceback to the console; a caller that shows "
                    "it itself (the batch script) turns this off")

    _timer = None
    _thread = None
    _state = None

    @classmethod
    def poll(cls, context):
        # scripts and the batch run name their strip: only the UI needs an active one
        return poll_run(cls, context, need_strip=not bpy.app.background)

    def _strip(self, context):
        editor = context.scene.sequence_editor
        if self.strip:
            found = editor.strips.get(self.strip) if editor else None
            if found is None:
                raise InputError(f"There is no strip named '{self.strip}' in the scene "
                                        f"'{context.scene.name}'.")
            return found
        return editor.active_strip if editor else None

    def _prepare(self, context):
        job = bridge.gather_job(context, self._strip(context), models_override=self.models_dir)
        lights, warnings = schedule_lights(context, job)
        return job, lights, warnings

    def _finish(self, context, job, result, warnings, seconds):
        for warning in [*warnings, *getattr(result, "warnings", ())]:
            self.report({'WARNING'}, str(warning))
        show_source_light(result)
        published = publish_numbered(job, result)
        added = add_result_strips(context, job, result)
        n = len(job.clip_frames)
        where = (f"added strip '{added[0].name}'" if added
                 else "no strip added (the other frames are not relit yet)")
        self.report({'INFO'}, f"Relit {n} frames of '{job.strip_name}' with {result.model} on "
                              f"{result.provider} in {seconds:.1f} s "
                              f"({result.resumed} resumed) into take {take_label(result)}, "
                              f"{result.out_dir}; {where}")
        return published

    # Synchronous: background mode, scripts, and tests.
    def execute(self, context):
        global last_error, last_result, last_published
        started = time.perf_counter()
        last_error, last_result, last_published = None, None, []
        try:
            job, lights, warnings = self._prepare(context)
            result = run_pipeline(job, lights, on_progress=progress_sink or _print_progress,
                                  log=log_sink or _print_log)
            last_published = self._finish(context, job, result, warnings,
                                          time.perf_counter() - started)
            last_result = result
        except RelightError as err:
            last_error = err
            self.report({'ERROR'}, str(err))
            return {'CANCELLED'}
        except KeyboardInterrupt:  # Ctrl-C in a console or batch run: a cancel like Esc
            last_error = Cancelled("Cancelled; the finished frames are kept, run again to "
                                   "resume.")
            self.report({'WARNING'}, str(last_error))
            return {'CANCELLED'}
        except Exception as err:  # a bug: one report line; its traceback once, on the console
            # Left to Blender, the traceback would be printed and then reported as the error's
            # text, which bpy.ops hands to scripts: twice, and as if it were a user error.
            last_error = err
            if self.show_traceback:
                traceback.print_exception(err)
            text = " ".join(str(err).split())
            self.report({'ERROR'}, f"Unexpected error ({type(err).__name__}: {text}); this is a "
                                   "bug, please report it with the console's traceback.")
            return {'CANCELLED'}
        return {'FINISHED'}

    # Interactive: a worker thread, polled by a timer.
    def invoke(self, context, event):
        if bpy.app.background:
            return self.execute(context)
        try:
            job, lights, warnings = self._prepare(context)
        except RelightError as err:
            self.report({'ERROR'}, str(err))
            return {'CANCELLED'}
        global running
        running = job.strip_name
        self._state = _WorkerState(job=job, warnings=warnings, started=time.perf_counter())
        self._thread = threading.Thread(target=self._state.run, args=(lights,), daemon=True)
        self._thread.start()
        wm = context.window_manager
        wm.progress_begin(0, max(1, len(job.clip_frames)))
        self._timer = wm.event_timer_add(0.2, window=context.window)
        wm.modal_handler_add(self)
        self.report({'INFO'}, f"Relighting '{job.strip_name}'... (Esc cancels)")
        return {'RUNNING_MODAL'}

    def modal(self, context, event):
        state = self._state
        if event.type == 'ESC':
            state.cancel.set()
            return {'RUNNING_MODAL'}  # consumed: Esc cancels the run, nothing else
        if event.type != 'TIMER':
            return {'PASS_THROUGH'}
        context.window_manager.progress_update(state.done)
        context.workspace.status_text_set(
            f"Relighting {state.job.strip_name}: {state.done}/{len(state.job.clip_frames)} "
            "frames (Esc cancels)")
        if self._thread.is_alive():
            return {'RUNNING_MODAL'}
        self._end_modal(context)
        if isinstance(state.error, Cancelled):
            self.report({'WARNING'}, f"{state.error} Run Relight again to resume.")
            return {'CANCELLED'}
        if isinstance(state.error, RelightError):
            self.report({'ERROR'}, str(state.error))
            return {'CANCELLED'}
        if state.error is not None:  # a bug: surface it with its traceback, never swallow it
            raise state.error
        self._finish(context, state.job, state.result, state.warnings,
                     time.perf_counter() - state.started)
        return {'FINISHED'}

    def _end_modal(self, context):
        global running
        running = None
        wm = context.window_manager
        wm.event_timer_remove(self._timer)
        wm.progress_end()
        context.workspace.status_text_set(None)


class _WorkerState:
    """What the worker thread shares with the modal operator: progress in, cancel flag out."""

    def __init__(self, job, warnings, started):
        self.job, self.warnings, self.started = job, warnings, started
        self.done = 0
        self.cancel = threading.Event()
        self.result = None
        self.error = None

    def progress(self, done, total=None, *_):
        self.done = int(done)

    def run(self, lights):
        try:
            self.result = run_pipeline(self.job, lights, on_progress=self.progress,
                                       should_cancel=self.cancel.is_set)
        except BaseException as err:  # handed to the main thread, which reports or re-raises
            self.error = err


def _print_progress(done, total=None, *_):
    # The pipeline reports before every frame; print each change once.
    if total and _print_progress.last != (done, total):
        _print_progress.last = (done, total)
        print(f"relight: {done}/{total} frames ({100.0 * done / total:.0f}%)", flush=True)


_print_progress.last = None


def _print_log(message: str) -> None:
    print(f"relight: {message}", flush=True)


classes = (RELIGHT_OT_relight_strip,)


register, unregister = bpy.utils.register_classes_factory(classes)
