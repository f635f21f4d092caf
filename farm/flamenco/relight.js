// SPDX-License-Identifier: GPL-3.0-or-later
// Flamenco 3 custom job type: relight one strip of a .blend file, split into frame chunks, then
// add the relit strip to the .blend and save it.
//
// Install: copy this file into the Manager's `scripts/` folder and restart the Manager. Each task
// runs `blender -b FILE.blend -P relight_batch.py -- --strip NAME --frames A-B ...` on a worker.
// Define a Flamenco variable `relight_batch` (flamenco-manager.yaml) holding the path of
// scripts/relight_batch.py on the workers, or type the path into the job's "relight_script".
// Per-frame outputs do not depend on the chunking, so chunks may run on any workers in any order;
// the last task runs the same command without --frames and with --save: every frame is found
// done, so it only adds the relit strip and saves the .blend.

const JOB_TYPE = {
    label: "Portrait Relight",
    description: "Relight a portrait footage strip with the Portrait Relight extension",
    settings: [
        { key: "blendfile", type: "string", subtype: "file_path", required: true,
          description: "The .blend file holding the strip and the lighting",
          eval: "bpy.data.filepath", visible: "web" },
        { key: "strip", type: "string", required: true,
          description: "Name of the movie or image strip to relight",
          eval: "C.scene.sequence_editor.active_strip.name" },
        { key: "frames", type: "string", required: true,
          description: "Scene frames to relight, 'START-END' (the strip's visible frames)",
          eval: "f'{C.scene.sequence_editor.active_strip.frame_final_start}-" +
                "{C.scene.sequence_editor.active_strip.frame_final_end - 1}'",
          evalInfo: { showLinkButton: true, description: "The active strip's visible frames" } },
        { key: "chunk_size", type: "int32", default: 25, propargs: { min: 1 },
          description: "Frames per task" },
        { key: "output_dir", type: "string", subtype: "dir_path", required: true,
          description: "Output folder, shared by all workers (one sub-folder per strip)",
          eval: "bpy.path.abspath(C.scene.relight.output_dir)" },

        // Lighting: at most one of these four; none uses the lighting set in the .blend.
        { key: "hdri", type: "string", subtype: "file_path", required: false,
          description: "Light with this HDRI file instead of the lighting set in the .blend" },
        { key: "studio", type: "string", required: false,
          description: "Light with one of Blender's studio HDRIs (city, courtyard, forest, " +
                       "interior, night, studio, sunrise, sunset)" },
        { key: "scene_lights", type: "bool", default: false,
          description: "Light with the scene's lamps instead of the lighting set in the .blend" },
        { key: "world", type: "bool", default: false,
          description: "Light with the scene's world instead of the lighting set in the .blend" },
        { key: "rotation", type: "string", required: false,
          description: "Turn the lighting by this many degrees; empty keeps the .blend's" },
        { key: "exposure", type: "string", required: false,
          description: "Scale the lighting by 2^EV; empty keeps the .blend's" },
        { key: "exposure_mode", type: "string", choices: ["blend", "keep", "physical"],
          default: "blend",
          description: "Keep the footage's exposure, or let the light's brightness set it " +
                       "('blend': as set in the .blend)" },

        { key: "preset", type: "string", required: false,
          description: "Quality preset (model); empty uses the one set in the .blend" },
        { key: "write_matte", type: "bool", default: false,
          description: "Also write the portrait matte" },
        { key: "add_strip", type: "bool", default: true,
          description: "Finish with a task that adds the relit strip to the .blend and saves it" },
        { key: "relight_script", type: "string", default: "{relight_batch}", visible: "web",
          description: "Path of scripts/relight_batch.py on the workers" },
    ],
};

function compileJob(job) {
    const settings = job.settings;
    const range = parseFrameRange(settings.frames);
    const args = batchArgs(settings);
    const chunkTasks = [];
    for (const [first, last] of chunkRange(range[0], range[1], settings.chunk_size)) {
        const task = author.Task(`relight-${first}-${last}`, "blender");
        task.addCommand(blenderCommand(settings, args.concat(["--frames", `${first}-${last}`]),
                                       last - first + 1));
        job.addTask(task);
        chunkTasks.push(task);
    }
    if (settings.add_strip === false) {
        return;
    }
    // The whole strip again, after every chunk: nothing is left to relight, so it adds the
    // relit strip (the same run: the same lighting and settings) and saves the .blend.
    const finish = author.Task("add-relit-strip", "blender");
    finish.addCommand(blenderCommand(settings, args.concat(["--save"]), 0));
    for (const task of chunkTasks) {
        finish.addDependency(task);
    }
    job.addTask(finish);
}

function blenderCommand(settings, scriptArgs, frameCount) {
    return author.Command("blender-render", {
        exe: "{blender}",
        exeArgs: "{blenderArgs}",
        argsBefore: [],
        blendfile: settings.blendfile,
        args: ["--python", settings.relight_script, "--"].concat(scriptArgs),
    }, frameCount);
}

// "START-END" or a single frame "N" -> [start, end]; anything else is refused at submission.
function parseFrameRange(text) {
    const m = /^\s*(-?\d+)\s*(?:-\s*(-?\d+)\s*)?$/.exec(String(text));
    if (!m) {
        throw `frames must look like 'START-END' (e.g. '1-250'), got '${text}'`;
    }
    const start = parseInt(m[1], 10);
    const end = m[2] === undefined ? start : parseInt(m[2], 10);
    if (end < start) {
        throw `frames '${text}' is empty: its end comes before its start`;
    }
    return [start, end];
}

// Consecutive [first, last] chunks that cover start..end exactly once, cut by Flamenco's own
// frameChunker. It reads '-' as a range separator, so scene frames (which may be negative) go
// in as positions 1..N and come back shifted; each chunk of a contiguous range is contiguous
// ("1-25", "26", or "26,27" for two frames).
function chunkRange(start, end, chunkSize) {
    const size = Math.max(1, Math.floor(Number(chunkSize) || 1));
    const chunks = frameChunker(`1-${end - start + 1}`, size);
    return chunks.map((chunk) => {
        const positions = String(chunk).match(/\d+/g).map((n) => parseInt(n, 10));
        const first = Math.min.apply(null, positions);
        const last = Math.max.apply(null, positions);
        return [start + first - 1, start + last - 1];
    });
}

// The batch script's options for the job's settings: the same for every task, so that the
// chunks and the last task are one run.
function batchArgs(settings) {
    const args = ["--strip", settings.strip, "--out", settings.output_dir];
    const lights = [];
    if (settings.hdri) {
        lights.push(["--hdri", settings.hdri]);
    }
    if (settings.studio) {
        lights.push(["--studio", settings.studio]);
    }
    if (settings.scene_lights) {
        lights.push(["--scene-lights"]);
    }
    if (settings.world) {
        lights.push(["--world"]);
    }
    if (lights.length > 1) {
        throw "choose one lighting: an HDRI file, a studio HDRI, the scene's lamps or its world";
    }
    for (const light of lights) {
        Array.prototype.push.apply(args, light);
    }
    for (const [key, flag, unit, limit] of [["rotation", "--rotation", "degrees", 36000],
                                             ["exposure", "--exposure", "stops", 128]]) {
        const text = settings[key] === undefined || settings[key] === null
            ? "" : String(settings[key]).trim();
        if (text === "") {
            continue;
        }
        const value = Number(text);
        if (!isFinite(value) || Math.abs(value) > limit) {
            throw `${key} must be a number of ${unit} between -${limit} and ${limit}, got '${text}'`;
        }
        args.push(flag, String(value));
    }
    if (settings.preset) {
        args.push("--preset", settings.preset);
    }
    if (settings.exposure_mode === "keep" || settings.exposure_mode === "physical") {
        args.push("--exposure-mode", settings.exposure_mode);
    } else if (settings.exposure_mode && settings.exposure_mode !== "blend") {
        throw `exposure_mode must be 'blend', 'keep' or 'physical', got '${settings.exposure_mode}'`;
    }
    if (settings.write_matte) {
        args.push("--matte");
    }
    return args;
}
