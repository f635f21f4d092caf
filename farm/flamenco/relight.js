// SPDX-License-Identifier: GPL-3.0-or-later
// Flamenco 3 custom job type: relight one strip of a .blend file, split into frame chunks.
//
// Install: copy this file into the Manager's `scripts/` folder and restart the Manager. Each task
// runs `blender -b FILE.blend -P relight_batch.py -- --strip NAME --frames A-B ...` on a worker.
// Define a Flamenco variable `relight_batch` (flamenco-manager.yaml) holding the path of
// scripts/relight_batch.py on the workers, or type the path into the job's "relight_script".
// Per-frame outputs do not depend on the chunking, so chunks may run on any workers in any order;
// afterwards, run Relight once in Blender: every frame is found done and the strip is added.

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
        { key: "hdri", type: "string", subtype: "file_path", required: false,
          description: "Light with this HDRI file instead of the lighting set in the .blend" },
        { key: "scene_lights", type: "bool", default: false,
          description: "Light with the scene's lamps instead of the lighting set in the .blend" },
        { key: "preset", type: "string", required: false,
          description: "Quality preset (model); empty uses the one set in the .blend" },
        { key: "write_matte", type: "bool", default: false,
          description: "Also write the portrait matte" },
        { key: "relight_script", type: "string", default: "{relight_batch}", visible: "web",
          description: "Path of scripts/relight_batch.py on the workers" },
    ],
};

function compileJob(job) {
    const settings = job.settings;
    const range = parseFrameRange(settings.frames);
    const args = batchArgs(settings);
    for (const [first, last] of chunkRange(range[0], range[1], settings.chunk_size)) {
        const task = author.Task(`relight-${first}-${last}`, "blender");
        task.addCommand(author.Command("blender-render", {
            exe: "{blender}",
            exeArgs: "{blenderArgs}",
            argsBefore: [],
            blendfile: settings.blendfile,
            args: ["--python", settings.relight_script, "--"].concat(
                args, ["--frames", `${first}-${last}`]),
        }, last - first + 1));
        job.addTask(task);
    }
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

// Consecutive [first, last] chunks that cover start..end exactly once.
function chunkRange(start, end, chunkSize) {
    const size = Math.max(1, Math.floor(Number(chunkSize) || 1));
    const chunks = [];
    for (let first = start; first <= end; first += size) {
        chunks.push([first, Math.min(end, first + size - 1)]);
    }
    return chunks;
}

function batchArgs(settings) {
    const args = ["--strip", settings.strip, "--out", settings.output_dir];
    if (settings.hdri) {
        args.push("--hdri", settings.hdri);
    } else if (settings.scene_lights) {
        args.push("--scene-lights");
    }
    if (settings.preset) {
        args.push("--preset", settings.preset);
    }
    if (settings.write_matte) {
        args.push("--matte");
    }
    return args;
}
