-- Catalogue schema v3: DuckDB views over the base tables tubes, tube_frames, frames, windows.
-- `mine query` (mining/catalog/views.py) creates the base tables, then runs this file.

-- Tubes chosen by co-selection: the mined result.
CREATE VIEW selected_tubes AS
SELECT * FROM tubes WHERE selected;

-- The call (mining/score/call.py): known, unknown, clutter or unclassified, in the column `call`.
-- Rows written before the column (call null) keep their old reading: known false = unknown,
-- known null = unclassified (then also where classifier evidence was low or the gate withdrew it).

-- Selected tubes a classifier looked at, in which unknown wins over the 80 COCO classes, and
-- whose object evidence says object: the unknown set, the discovery candidates.
CREATE VIEW unknown_tubes AS
SELECT * FROM tubes WHERE selected AND coalesce(call = 'unknown', known = false);

-- Selected tubes that are one of the 80 COCO classes (category names which).
CREATE VIEW known_tubes AS
SELECT * FROM tubes WHERE selected AND known = true;

-- Selected tubes unknown wins in, but whose object evidence says not an object (object_prob
-- below score.unknown_min_object: vegetation, verges, masks spilling over the background):
-- kept out of the unknown set.
CREATE VIEW clutter_tubes AS
SELECT * FROM tubes WHERE selected AND call = 'clutter';

-- Selected tubes no classifier looked at (classified_frames = 0: a class-agnostic proposer
-- alone): neither known nor unknown.
CREATE VIEW unclassified_tubes AS
SELECT * FROM tubes WHERE selected AND coalesce(call = 'unclassified', known IS NULL);

-- A tube's score and the terms that make it. score_model says which unary made the score:
--   calibrated: natural-log odds that the tube is an object; the theta_* columns add up to it, so
--     re-weighting what carried a tube is one SELECT, e.g. without the classifier's term:
--       SELECT tube_id, score - theta_class AS s FROM tube_scores ORDER BY s DESC LIMIT 100
--   reference: REFERENCE's β·(α·score_motion + (1−α)·score_mask) + (1−β)·score_objectness (theta_* null):
--       SELECT tube_id, 0.5 * score_motion + 2 * score_mask + score_objectness AS s
--       FROM tube_scores ORDER BY s DESC LIMIT 100
-- score_motion / score_mask / score_objectness are REFERENCE's terms under both models.
-- score_version (<score_model>-<hash of its parameters>): scores of two catalogues compare only where it agrees.
CREATE VIEW tube_scores AS
SELECT tube_id, dataset, sequence, n_frames, n_observed,
       score, score_model, score_version, theta_prior, theta_motion, theta_mask, theta_objectness, theta_shape, theta_class,
       score_motion, score_mask, score_objectness,
       selected, call, object_prob, known, category, category_prob, classified_frames, class_evidence
FROM tubes;

-- Every frame of every tube with the tube's class and selection (the 3D track per tube).
CREATE VIEW tube_tracks AS
SELECT f.*, t.category, t.known, t.call, t.selected, t.score AS tube_score
FROM tube_frames AS f
JOIN tubes AS t USING (dataset, sequence, tube_id);

-- While a job runs: the final tubes, plus the tubes of the windows finished so far in the
-- sequences not stitched yet (per-window pieces, `provisional` = true, with their window;
-- a tube crossing a window border appears once per window until the sequence is stitched).
-- The final views above never show provisional rows.
CREATE VIEW provisional_tubes AS
SELECT t.*, CAST(NULL AS VARCHAR) AS "window", false AS provisional FROM tubes AS t
UNION ALL BY NAME
SELECT p.*, true AS provisional FROM _part_tubes AS p
JOIN windows AS w ON w.dataset = p.dataset AND w.sequence = p.sequence AND w."window" = p."window"
WHERE w.status = 'done'
  AND NOT EXISTS (SELECT 1 FROM tubes AS t WHERE t.dataset = p.dataset AND t.sequence = p.sequence);

-- Their frames: a provisional piece's frames in its window's core only (each frame once per window).
CREATE VIEW provisional_tube_frames AS
SELECT f.*, CAST(NULL AS VARCHAR) AS "window", false AS provisional FROM tube_frames AS f
UNION ALL BY NAME
SELECT p.* EXCLUDE (core, posterior, class_weight, footpoint_cam, velocity_cam), true AS provisional
FROM _part_tube_frames AS p
JOIN windows AS w ON w.dataset = p.dataset AND w.sequence = p.sequence AND w."window" = p."window"
WHERE w.status = 'done' AND p.core
  AND NOT EXISTS (SELECT 1 FROM tubes AS t WHERE t.dataset = p.dataset AND t.sequence = p.sequence);

-- What people decided about the tubes (`mine view`, `mine label`): one row per labelled tube,
-- the replay of its events in the `labels` table (mining/catalog/labels.py) in time order.
-- verdict: the last verdict set (object, not_object, part_of, duplicate; null when unset);
-- tags: the tags whose last event set them, sorted; tag: the most recently set of them (the
-- name `mine export --category-from tag` gives the tube); labelled_at / labelled_by: the
-- last event's time and author; labelled_via: how the last event was written (view, cli or
-- propagated); source_tube / source_distance: for a propagated last event (`mine label --like`),
-- the tube whose decision it copied and the cosine distance of their descriptors (else null).
-- A tube whose every decision was taken back is not here.
CREATE VIEW tube_labels AS
WITH ordered AS (
    SELECT *, row_number() OVER (PARTITION BY dataset, sequence, tube_id, kind,
                                 CASE WHEN kind = 'tag' THEN value END
                                 ORDER BY "at" DESC, label_id DESC) AS newest
    FROM labels
),
verdicts AS (
    SELECT dataset, sequence, tube_id, value AS verdict FROM ordered
    WHERE kind = 'verdict' AND newest = 1 AND op = 'set'
),
tags AS (
    SELECT dataset, sequence, tube_id, list(value ORDER BY value) AS tags, arg_max(value, "at") AS tag
    FROM ordered WHERE kind = 'tag' AND newest = 1 AND op = 'set'
    GROUP BY dataset, sequence, tube_id
),
touched AS (
    SELECT dataset, sequence, tube_id, max("at") AS labelled_at, arg_max(author, "at") AS labelled_by,
           arg_max(via, "at") AS labelled_via, arg_max(source_tube, "at") AS source_tube,
           arg_max(distance, "at") AS source_distance
    FROM labels GROUP BY dataset, sequence, tube_id
)
SELECT t.dataset, t.sequence, t.tube_id, v.verdict, coalesce(g.tags, []::VARCHAR[]) AS tags, g.tag,
       t.labelled_at, t.labelled_by, t.labelled_via, t.source_tube, t.source_distance
FROM touched AS t
LEFT JOIN verdicts AS v ON v.dataset = t.dataset AND v.sequence = t.sequence AND v.tube_id = t.tube_id
LEFT JOIN tags AS g ON g.dataset = t.dataset AND g.sequence = t.sequence AND g.tube_id = t.tube_id
WHERE v.verdict IS NOT NULL OR g.tags IS NOT NULL;

-- Every tube with its labels (null / [] where none) and its group of the unknown set (`mine group`:
-- tube_group, −1 noise, null where not grouped): what `mine export --where`, `mine label --where` and
-- the gallery filter read, so a predicate may say `verdict = 'object'`, `list_contains(tags, 'barrier')`
-- or `tube_group = 3`.
CREATE VIEW labelled_tubes AS
SELECT t.*, l.verdict, coalesce(l.tags, []::VARCHAR[]) AS tags, l.tag, l.labelled_at, l.labelled_by,
       l.labelled_via, l.source_tube, l.source_distance, g."group" AS tube_group, g.probability AS group_probability
FROM tubes AS t
LEFT JOIN tube_labels AS l ON l.dataset = t.dataset AND l.sequence = t.sequence AND l.tube_id = t.tube_id
LEFT JOIN tube_groups AS g ON g.dataset = t.dataset AND g.sequence = t.sequence AND g.tube_id = t.tube_id;
