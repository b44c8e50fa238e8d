-- Catalogue schema v2: DuckDB views over the base tables tubes, tube_frames, frames, windows.
-- `mine query` (mining/catalog/views.py) creates the base tables, then runs this file.

-- Tubes chosen by co-selection: the mined result.
CREATE VIEW selected_tubes AS
SELECT * FROM tubes WHERE selected;

-- Selected tubes a classifier looked at and found none of the 80 COCO classes in: the
-- discovery candidates. (`NOT known` is null for unclassified tubes, so they are not here.)
CREATE VIEW unknown_tubes AS
SELECT * FROM tubes WHERE selected AND known = false;

-- Selected tubes that are one of the 80 COCO classes (category names which).
CREATE VIEW known_tubes AS
SELECT * FROM tubes WHERE selected AND known = true;

-- Selected tubes no classifier looked at (a class-agnostic proposer alone, or too little
-- classifier evidence): neither known nor unknown.
CREATE VIEW unclassified_tubes AS
SELECT * FROM tubes WHERE selected AND known IS NULL;

-- A tube's score and its components: re-ranking by another weighting is one SELECT, e.g.
--   SELECT tube_id, 0.5 * score_motion + 2 * score_mask + score_objectness AS s
--   FROM tube_scores ORDER BY s DESC LIMIT 100
CREATE VIEW tube_scores AS
SELECT tube_id, dataset, sequence, n_frames, n_observed,
       score, score_motion, score_mask, score_objectness,
       selected, known, category, category_prob, classified_frames, class_evidence
FROM tubes;

-- Every frame of every tube with the tube's class and selection (the 3D track per tube).
CREATE VIEW tube_tracks AS
SELECT f.*, t.category, t.known, t.selected, t.score AS tube_score
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
