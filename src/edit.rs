//! The edit language of `colf-edit` (its contract: `docs/formats.md`): a JSON list of ops applied in
//! order to a codes file. Slot indices refer to the slots as they stand when the op runs.
//!
//! Parsing is separate from applying, and both report the op's index and the offending field,
//! so a script author sees `op 2 (rotate): field `axis`: …` and nothing is written.

use crate::codes::{Codes, Slot};
use anyhow::{anyhow, bail, Context, Result};
use glam::{DMat4, DQuat, DVec3};
use serde_json::{Map, Value};

/// Which slots an op applies to.
#[derive(Clone, Debug, PartialEq)]
pub enum Selection {
    All,
    Indices(Vec<usize>),
    /// The one slot whose frame origin lies nearest `point` (the first on ties), refused when
    /// it is farther than `within`: scripts that name an object by where it stands, not by
    /// the index an encoding happened to give it. With `seen_from`, the distance is the frame
    /// origin's from the line of sight from that point through `point` (in front of it): an
    /// encoding from one view knows an object's direction well but its depth only roughly, so
    /// the slot that draws it lies on that line, not necessarily near `point`.
    Near {
        point: DVec3,
        within: Option<f64>,
        seen_from: Option<DVec3>,
    },
}

/// One edit operation.
#[derive(Clone, Debug, PartialEq)]
pub enum Op {
    /// Move slots by a world-space vector.
    Translate {
        slots: Selection,
        by: DVec3,
    },
    /// Rotate slots about `axis` through `pivot` (world space).
    Rotate {
        slots: Selection,
        axis: DVec3,
        degrees: f64,
        pivot: DVec3,
    },
    Delete {
        slots: Selection,
    },
    Keep {
        slots: Selection,
    },
    /// Append copies of slots, moved by `by`.
    Duplicate {
        slots: Selection,
        by: DVec3,
    },
    /// Append slots of another codes file, in their own frames.
    Merge {
        from: String,
        slots: Selection,
    },
    /// Replace the background latent with another file's.
    Background {
        from: String,
    },
    /// Drop slots whose attention mass is below `min_mass`.
    Prune {
        min_mass: f64,
    },
}

impl Op {
    /// The op's name as written in JSON.
    pub fn name(&self) -> &'static str {
        match self {
            Op::Translate { .. } => "translate",
            Op::Rotate { .. } => "rotate",
            Op::Delete { .. } => "delete",
            Op::Keep { .. } => "keep",
            Op::Duplicate { .. } => "duplicate",
            Op::Merge { .. } => "merge",
            Op::Background { .. } => "background",
            Op::Prune { .. } => "prune",
        }
    }
}

/// Fields each op accepts (besides `op` and a free-form `comment`): anything else is a typo
/// that would otherwise be silently ignored.
fn allowed_fields(op: &str) -> Option<&'static [&'static str]> {
    Some(match op {
        "translate" => &["slots", "by"],
        "rotate" => &["slots", "axis", "degrees", "pivot"],
        "delete" | "keep" => &["slots"],
        "duplicate" => &["slots", "by"],
        "merge" => &["from", "slots"],
        "background" => &["from"],
        "prune" => &["min_mass"],
        _ => return None,
    })
}

/// Reads the fields of one op object, with errors naming the field.
struct Fields<'a> {
    map: &'a Map<String, Value>,
}

impl Fields<'_> {
    fn get(&self, field: &str) -> Result<&Value> {
        self.map
            .get(field)
            .ok_or_else(|| anyhow!("field `{field}` is missing"))
    }

    fn number(&self, field: &str) -> Result<f64> {
        let v = self.get(field)?;
        let x = v
            .as_f64()
            .ok_or_else(|| anyhow!("field `{field}`: expected a number, got {v}"))?;
        if !x.is_finite() {
            bail!("field `{field}`: not a finite number");
        }
        Ok(x)
    }

    fn vec3(&self, field: &str) -> Result<DVec3> {
        let v = self.get(field)?;
        let items = v
            .as_array()
            .filter(|a| a.len() == 3)
            .ok_or_else(|| anyhow!("field `{field}`: expected an array of 3 numbers, got {v}"))?;
        let mut out = [0.0; 3];
        for (o, item) in out.iter_mut().zip(items) {
            *o = item
                .as_f64()
                .filter(|x| x.is_finite())
                .ok_or_else(|| anyhow!("field `{field}`: `{item}` is not a finite number"))?;
        }
        Ok(DVec3::from_array(out))
    }

    fn vec3_or(&self, field: &str, default: DVec3) -> Result<DVec3> {
        if self.map.contains_key(field) {
            self.vec3(field)
        } else {
            Ok(default)
        }
    }

    fn string(&self, field: &str) -> Result<String> {
        let v = self.get(field)?;
        let s = v
            .as_str()
            .ok_or_else(|| anyhow!("field `{field}`: expected a string, got {v}"))?;
        if s.is_empty() {
            bail!("field `{field}`: empty path");
        }
        Ok(s.to_string())
    }

    fn selection(&self, field: &str) -> Result<Selection> {
        let v = self.get(field)?;
        if v.as_str() == Some("all") {
            return Ok(Selection::All);
        }
        if let Some(near) = v.as_object() {
            return near_selection(field, near);
        }
        let items = v.as_array().ok_or_else(|| {
            anyhow!("field `{field}`: expected \"all\", an array of slot indices or {{\"near\": [x, y, z]}}, got {v}")
        })?;
        let indices = items
            .iter()
            .map(|item| {
                item.as_u64()
                    .map(|i| i as usize)
                    .ok_or_else(|| anyhow!("field `{field}`: `{item}` is not a slot index"))
            })
            .collect::<Result<Vec<_>>>()?;
        Ok(Selection::Indices(indices))
    }

    fn selection_or_all(&self, field: &str) -> Result<Selection> {
        if self.map.contains_key(field) {
            self.selection(field)
        } else {
            Ok(Selection::All)
        }
    }
}

/// `{"near": [x, y, z], "within": r, "seen_from": [x, y, z]}` (`within` optional, a positive
/// number; `seen_from` optional, a point other than `near`).
fn near_selection(field: &str, near: &Map<String, Value>) -> Result<Selection> {
    if let Some(extra) = near
        .keys()
        .find(|k| !["near", "within", "seen_from"].contains(&k.as_str()))
    {
        bail!("field `{field}`: unknown key `{extra}` (allowed: near, within, seen_from)");
    }
    let f = Fields { map: near };
    let point = f.vec3("near").with_context(|| format!("field `{field}`"))?;
    let seen_from = if near.contains_key("seen_from") {
        let eye = f
            .vec3("seen_from")
            .with_context(|| format!("field `{field}`"))?;
        if (point - eye).length() <= 1e-9 * (1.0 + point.length()) {
            bail!("field `{field}`: field `seen_from`: must differ from `near` (it is the start of the line of sight through it)");
        }
        Some(eye)
    } else {
        None
    };
    let within = if near.contains_key("within") {
        let r = f
            .number("within")
            .with_context(|| format!("field `{field}`"))?;
        if r <= 0.0 {
            bail!("field `{field}`: field `within`: must be positive, got {r}");
        }
        Some(r)
    } else {
        None
    };
    Ok(Selection::Near {
        point,
        within,
        seen_from,
    })
}

/// Parses one op. The error is the text that follows `op N` in the message: `: …` before the
/// op's name is known, ` (name): …` after.
fn parse_op(value: &Value) -> std::result::Result<Op, String> {
    let map = value
        .as_object()
        .ok_or_else(|| format!(": expected an object, got {value}"))?;
    let name = match map.get("op") {
        None => return Err(": field `op` is missing".into()),
        Some(v) => v
            .as_str()
            .ok_or_else(|| format!(": field `op`: expected a string, got {v}"))?,
    };
    let allowed = allowed_fields(name).ok_or_else(|| {
        format!(": field `op`: unknown op `{name}` (known: translate, rotate, delete, keep, duplicate, merge, background, prune)")
    })?;
    let in_op = |e: anyhow::Error| format!(" ({name}): {e:#}");
    if let Some(extra) = map
        .keys()
        .find(|k| *k != "op" && *k != "comment" && !allowed.contains(&k.as_str()))
    {
        return Err(in_op(anyhow!(
            "unknown field `{extra}` (allowed: {})",
            allowed.join(", ")
        )));
    }
    let f = Fields { map };
    let op = || -> Result<Op> {
        Ok(match name {
            "translate" => Op::Translate {
                slots: f.selection("slots")?,
                by: f.vec3("by")?,
            },
            "rotate" => {
                let axis = f.vec3("axis")?;
                if unit_axis(axis).is_none() {
                    bail!("field `axis`: the rotation axis must not be zero");
                }
                Op::Rotate {
                    slots: f.selection("slots")?,
                    axis,
                    degrees: f.number("degrees")?,
                    pivot: f.vec3_or("pivot", DVec3::ZERO)?,
                }
            }
            "delete" => Op::Delete {
                slots: f.selection("slots")?,
            },
            "keep" => Op::Keep {
                slots: f.selection("slots")?,
            },
            "duplicate" => Op::Duplicate {
                slots: f.selection("slots")?,
                by: f.vec3_or("by", DVec3::ZERO)?,
            },
            "merge" => Op::Merge {
                from: f.string("from")?,
                slots: f.selection_or_all("slots")?,
            },
            "background" => Op::Background {
                from: f.string("from")?,
            },
            "prune" => {
                let min_mass = f.number("min_mass")?;
                if !(0.0..=1.0).contains(&min_mass) {
                    bail!("field `min_mass`: {min_mass} is outside [0, 1]");
                }
                Op::Prune { min_mass }
            }
            _ => unreachable!("allowed_fields knows every op"),
        })
    };
    op().map_err(in_op)
}

/// Parses an edits document: `{"ops": [...]}` or a bare array. `name` prefixes errors.
pub fn parse_edits(bytes: &[u8], name: &str) -> Result<Vec<Op>> {
    let doc: Value = crate::io::parse_json(bytes, name)?;
    let list = match &doc {
        Value::Array(items) => items,
        Value::Object(map) => {
            if let Some(extra) = map.keys().find(|k| *k != "ops" && *k != "comment") {
                bail!("{name}: unknown top-level field `{extra}` (expected `ops`)");
            }
            map.get("ops")
                .and_then(Value::as_array)
                .ok_or_else(|| anyhow!("{name}: expected `ops` to be an array of ops"))?
        }
        _ => bail!("{name}: expected {{\"ops\": [...]}} or an array of ops"),
    };
    list.iter()
        .enumerate()
        .map(|(i, v)| parse_op(v).map_err(|why| anyhow!("{name}: op {i}{why}")))
        .collect()
}

/// The distance of `q` from the half-line that starts at `start` and runs along `direction`
/// (not zero): from its foot on the line when that lies ahead of `start`, else from `start`.
fn distance_to_half_line(q: DVec3, start: DVec3, direction: DVec3) -> f64 {
    let along = direction.normalize();
    let offset = q - start;
    let ahead = offset.dot(along).max(0.0);
    (offset - along * ahead).length()
}

/// The indices a selection names among `slots` as they stand; `All` → every slot.
fn resolve(selection: &Selection, slots: &[Slot]) -> Result<Vec<usize>> {
    let count = slots.len();
    match selection {
        Selection::Near {
            point,
            within,
            seen_from,
        } => {
            let distance = |s: &Slot| {
                let origin = s.slot_to_world.w_axis.truncate();
                match seen_from {
                    None => (origin - *point).length(),
                    Some(eye) => distance_to_half_line(origin, *eye, *point - *eye),
                }
            };
            let what = match seen_from {
                None => "",
                Some(_) => " on the line of sight",
            };
            // `min_by` keeps the first of equal minima.
            let Some((nearest, d)) = slots
                .iter()
                .map(distance)
                .enumerate()
                .min_by(|a, b| a.1.total_cmp(&b.1))
            else {
                bail!(
                    "field `slots`: no slot near [{}, {}, {}]: there are no slots at this point",
                    point.x,
                    point.y,
                    point.z
                );
            };
            if let Some(r) = within.filter(|r| d > *r) {
                bail!(
                    "field `slots`: no slot within {r}{what} of [{}, {}, {}] (the nearest, slot {nearest}, is {d:.3} away)",
                    point.x, point.y, point.z
                );
            }
            Ok(vec![nearest])
        }
        Selection::All => Ok((0..count).collect()),
        Selection::Indices(list) => {
            if let Some(&bad) = list.iter().find(|&&i| i >= count) {
                bail!(
                    "field `slots`: slot {bad} does not exist (there are {count} slots at this point)"
                );
            }
            let mut out = list.clone();
            out.sort_unstable();
            out.dedup();
            Ok(out)
        }
    }
}

/// `axis` as a unit vector (`camera::unit_vector`: scaled first, so [0, 0, 1e200] still
/// turns about +Z); `None` for the zero vector.
pub fn unit_axis(axis: DVec3) -> Option<DVec3> {
    crate::camera::unit_vector(axis)
}

/// World-space rotation by `degrees` about `axis` (any finite non-zero vector) through `pivot`.
pub fn rotation_about(axis: DVec3, degrees: f64, pivot: DVec3) -> DMat4 {
    let axis = unit_axis(axis).unwrap_or(DVec3::Z);
    DMat4::from_translation(pivot)
        * DMat4::from_quat(DQuat::from_axis_angle(axis, degrees.to_radians()))
        * DMat4::from_translation(-pivot)
}

/// Loads another codes file for merge/background, checking that it comes from the same model
/// and has the same latent size.
fn load_compatible(path: &str, codes: &Codes) -> Result<Codes> {
    let other = Codes::read(path).with_context(|| "field `from`".to_string())?;
    if other.model != codes.model {
        bail!(
            "field `from`: {path} was encoded by model `{}`, these codes by `{}`; slots of different models cannot be rendered together",
            other.model,
            codes.model
        );
    }
    if other.dim() != codes.dim() {
        bail!(
            "field `from`: {path} has latent size {}, these codes {}",
            other.dim(),
            codes.dim()
        );
    }
    Ok(other)
}

/// Applies one op in place.
pub fn apply_op(codes: &mut Codes, op: &Op) -> Result<()> {
    match op {
        Op::Translate { slots, by } => {
            let t = DMat4::from_translation(*by);
            for i in resolve(slots, &codes.slots)? {
                codes.slots[i].slot_to_world = t * codes.slots[i].slot_to_world;
            }
        }
        Op::Rotate {
            slots,
            axis,
            degrees,
            pivot,
        } => {
            let r = rotation_about(*axis, *degrees, *pivot);
            for i in resolve(slots, &codes.slots)? {
                codes.slots[i].slot_to_world = r * codes.slots[i].slot_to_world;
            }
        }
        Op::Delete { slots } => {
            let doomed = resolve(slots, &codes.slots)?;
            let mut index = 0;
            codes.slots.retain(|_| {
                let keep = doomed.binary_search(&index).is_err();
                index += 1;
                keep
            });
        }
        Op::Keep { slots } => {
            let kept = resolve(slots, &codes.slots)?;
            codes.slots = kept.iter().map(|&i| codes.slots[i].clone()).collect();
        }
        Op::Duplicate { slots, by } => {
            let t = DMat4::from_translation(*by);
            for i in resolve(slots, &codes.slots)? {
                let mut copy: Slot = codes.slots[i].clone();
                copy.slot_to_world = t * copy.slot_to_world;
                codes.slots.push(copy);
            }
        }
        Op::Merge { from, slots } => {
            let other = load_compatible(from, codes)?;
            for i in resolve(slots, &other.slots).with_context(|| format!("in {from}"))? {
                let mut slot = other.slots[i].clone();
                if slot.source.is_empty() {
                    slot.source = format!("{from}#{i}");
                }
                codes.slots.push(slot);
            }
        }
        Op::Background { from } => {
            codes.background = load_compatible(from, codes)?.background;
        }
        Op::Prune { min_mass } => {
            codes.slots.retain(|s| s.mass as f64 >= *min_mass);
        }
    }
    Ok(())
}

/// Applies every op in order; an error names the op's index and field. `codes` is only
/// changed when every op succeeds. After each op the codes must pass the checks of a codes
/// file (`Codes::validate`: slot count, frames finite in f32), so the op that breaks them is
/// the one named, and the slot count stays bounded however many ops duplicate.
pub fn apply_edits(codes: &Codes, ops: &[Op], name: &str) -> Result<Codes> {
    let mut edited = codes.clone();
    for (i, op) in ops.iter().enumerate() {
        apply_op(&mut edited, op)
            .and_then(|()| edited.validate())
            .map_err(|e| anyhow!("{name}: op {i} ({}): {e:#}", op.name()))?;
    }
    Ok(edited)
}

/// The Euclidean norm of `values`, in f64 and scaled by the largest magnitude, so that finite
/// latents near 3e30 (whose squares overflow f32) still have a finite norm.
fn scaled_norm(values: &[f32]) -> f64 {
    let largest = values.iter().fold(0.0f64, |m, &v| m.max((v as f64).abs()));
    if largest == 0.0 || !largest.is_finite() {
        return largest;
    }
    largest
        * values
            .iter()
            .map(|&v| (v as f64 / largest).powi(2))
            .sum::<f64>()
            .sqrt()
}

/// The JSON summary printed by `colf-edit --inspect`.
pub fn inspect(codes: &Codes) -> Value {
    let slots: Vec<Value> = codes
        .slots
        .iter()
        .enumerate()
        .map(|(i, s)| {
            let origin = s.slot_to_world.w_axis.truncate();
            serde_json::json!({
                "index": i,
                "mass": s.mass,
                "origin": [origin.x, origin.y, origin.z],
                "source": s.source,
                "latent_norm": scaled_norm(&s.latent),
            })
        })
        .collect();
    serde_json::json!({
        "format": crate::codes::CODES_FORMAT,
        "model": codes.model,
        "dim": codes.dim(),
        "num_slots": codes.slots.len(),
        "total_mass": codes.slots.iter().map(|s| s.mass).sum::<f32>(),
        "slots": slots,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::codes::tests::sample;

    fn ops(text: &str) -> Vec<Op> {
        parse_edits(text.as_bytes(), "e.json").unwrap()
    }

    fn err(text: &str) -> String {
        format!("{:#}", parse_edits(text.as_bytes(), "e.json").unwrap_err())
    }

    fn origin(codes: &Codes, i: usize) -> DVec3 {
        codes.slots[i].slot_to_world.w_axis.truncate()
    }

    #[test]
    fn translate_and_rotate_about_a_pivot() {
        let codes = sample(3);
        let edited = apply_edits(
            &codes,
            &ops(r#"[{"op":"translate","slots":[2],"by":[1,0,0]},
                     {"op":"rotate","slots":[1],"axis":[0,0,1],"degrees":90,"pivot":[1,1,0]}]"#),
            "e",
        )
        .unwrap();
        assert!((origin(&edited, 2) - DVec3::new(3.0, 0.0, 0.0)).length() < 1e-12);
        // Slot 1 sits at (1,0,0); 90° about +Z through (1,1,0) takes it to (2,1,0).
        assert!((origin(&edited, 1) - DVec3::new(2.0, 1.0, 0.0)).length() < 1e-12);
        let x_axis = edited.slots[1].slot_to_world.x_axis.truncate();
        assert!((x_axis - DVec3::Y).length() < 1e-12);
        assert_eq!(edited.slots[0], codes.slots[0]);
    }

    #[test]
    fn delete_keep_duplicate_prune_and_all() {
        let codes = sample(4); // masses 0, .1, .2, .3
        let e = apply_edits(
            &codes,
            &ops(r#"{"ops":[{"op":"delete","slots":[0,2]}]}"#),
            "e",
        )
        .unwrap();
        assert_eq!(
            e.slots,
            vec![codes.slots[1].clone(), codes.slots[3].clone()]
        );
        let e = apply_edits(&codes, &ops(r#"[{"op":"keep","slots":[3,1]}]"#), "e").unwrap();
        assert_eq!(
            e.slots,
            vec![codes.slots[1].clone(), codes.slots[3].clone()]
        );
        let e = apply_edits(
            &codes,
            &ops(r#"[{"op":"duplicate","slots":[1],"by":[0,2,0]}]"#),
            "e",
        )
        .unwrap();
        assert_eq!(e.slots.len(), 5);
        assert!((origin(&e, 4) - DVec3::new(1.0, 2.0, 0.0)).length() < 1e-12);
        assert_eq!(e.slots[4].latent, codes.slots[1].latent);
        let e = apply_edits(&codes, &ops(r#"[{"op":"prune","min_mass":0.15}]"#), "e").unwrap();
        assert_eq!(e.slots.len(), 2);
        let e = apply_edits(
            &codes,
            &ops(
                r#"[{"op":"translate","slots":"all","by":[0,0,1]}, {"op":"delete","slots":"all"}]"#,
            ),
            "e",
        )
        .unwrap();
        assert!(e.slots.is_empty());
    }

    #[test]
    fn indices_refer_to_slots_as_they_stand() {
        let codes = sample(3);
        // After deleting slot 0, the old slot 2 is slot 1.
        let e = apply_edits(
            &codes,
            &ops(r#"[{"op":"delete","slots":[0]},{"op":"translate","slots":[1],"by":[0,5,0]}]"#),
            "e",
        )
        .unwrap();
        assert!((origin(&e, 1) - DVec3::new(2.0, 5.0, 0.0)).length() < 1e-12);
    }

    /// A slot named by where it stands: the nearest frame origin, as the slots stand when the
    /// op runs; `within` refuses a point with no slot close enough.
    #[test]
    fn slots_are_chosen_by_position() {
        let codes = sample(4); // origins (i, 0, 0)
        let e = apply_edits(
            &codes,
            &ops(r#"[{"op":"delete","slots":{"near":[2.2,0.3,0]}},
                     {"op":"translate","slots":{"near":[2.9,0,0],"within":0.5},"by":[0,4,0]}]"#),
            "e",
        )
        .unwrap();
        assert_eq!(e.slots.len(), 3);
        assert!((origin(&e, 2) - DVec3::new(3.0, 4.0, 0.0)).length() < 1e-12);
        // Ties go to the first slot.
        let e = apply_edits(
            &codes,
            &ops(r#"[{"op":"keep","slots":{"near":[0.5,0,0]}}]"#),
            "e",
        )
        .unwrap();
        assert_eq!(e.slots, vec![codes.slots[0].clone()]);
        let far = apply_edits(
            &codes,
            &ops(r#"[{"op":"delete","slots":{"near":[1,5,0],"within":2}}]"#),
            "e",
        )
        .unwrap_err();
        assert!(
            format!("{far:#}")
                .contains("no slot within 2 of [1, 5, 0] (the nearest, slot 1, is 5.000 away)"),
            "{far:#}"
        );
        let none = apply_edits(
            &sample(0),
            &ops(r#"[{"op":"delete","slots":{"near":[0,0,0]}}]"#),
            "e",
        )
        .unwrap_err();
        assert!(
            format!("{none:#}").contains("no slots at this point"),
            "{none:#}"
        );
        for (text, why) in [
            (
                r#"[{"op":"delete","slots":{"near":[0,0]}}]"#,
                "field `near`: expected an array of 3 numbers",
            ),
            (
                r#"[{"op":"delete","slots":{"near":[0,0,0],"within":0}}]"#,
                "must be positive",
            ),
            (
                r#"[{"op":"delete","slots":{"near":[0,0,0],"radius":1}}]"#,
                "unknown key `radius`",
            ),
        ] {
            assert!(err(text).contains(why), "{}", err(text));
        }
    }

    /// `seen_from`: the distance is from the line of sight through `near`, so a slot placed at
    /// the wrong depth along it is still found, and one beside it is not.
    #[test]
    fn slots_are_chosen_on_a_line_of_sight() {
        let codes = sample(4); // origins (i, 0, 0)
                               // Seen from (0, -4, 0), the line through (2, 4, 0) crosses y = 0 at x = 1: slot 1 lies
                               // on it, though slot 2 is nearest the point itself.
        let e = apply_edits(
            &codes,
            &ops(r#"[{"op":"delete","slots":{"near":[2,4,0],"seen_from":[0,-4,0],"within":0.1}}]"#),
            "e",
        )
        .unwrap();
        let left: Vec<f64> = e.slots.iter().map(|s| s.slot_to_world.w_axis.x).collect();
        assert_eq!(left, vec![0.0, 2.0, 3.0]);
        // Without the line of sight the nearest to (2, 4, 0) is slot 2, 4 away.
        let plain = apply_edits(
            &codes,
            &ops(r#"[{"op":"delete","slots":{"near":[2,4,0]}}]"#),
            "e",
        )
        .unwrap();
        let left: Vec<f64> = plain
            .slots
            .iter()
            .map(|s| s.slot_to_world.w_axis.x)
            .collect();
        assert_eq!(left, vec![0.0, 1.0, 3.0]);
        // Behind the eye counts from the eye: looking away from every slot, the nearest is
        // the one nearest the eye.
        let behind = apply_edits(
            &codes,
            &ops(r#"[{"op":"delete","slots":{"near":[3.2,-8,0],"seen_from":[3.2,-4,0],"within":1}}]"#),
            "e",
        )
        .unwrap_err();
        assert!(
            format!("{behind:#}").contains(
                "no slot within 1 on the line of sight of [3.2, -8, 0] (the nearest, slot 3, is 4.005 away)"
            ),
            "{behind:#}"
        );
        assert!(
            err(r#"[{"op":"delete","slots":{"near":[1,2,3],"seen_from":[1,2,3]}}]"#)
                .contains("field `seen_from`: must differ from `near`"),
        );
        assert!(
            err(r#"[{"op":"delete","slots":{"near":[1,2,3],"seen_from":[1,2]}}]"#)
                .contains("field `seen_from`: expected an array of 3 numbers"),
        );
    }

    #[test]
    fn parse_errors_name_the_op_and_field() {
        let cases = [
            (
                r#"[{"op":"translate","slots":[0]}]"#,
                "e.json: op 0 (translate): field `by` is missing",
            ),
            (
                r#"[{"op":"translate","slots":[0],"by":[1,2]}]"#,
                "op 0 (translate): field `by`: expected an array of 3",
            ),
            (
                r#"[{"op":"delete","slots":[0]},{"op":"spin"}]"#,
                "op 1: field `op`: unknown op `spin`",
            ),
            (
                r#"[{"op":"rotate","slots":[0],"axis":[0,0,0],"degrees":3}]"#,
                "op 0 (rotate): field `axis`",
            ),
            (
                r#"[{"op":"rotate","slots":[0],"axis":[0,0,1],"degrees":"x"}]"#,
                "op 0 (rotate): field `degrees`",
            ),
            (
                r#"[{"op":"delete","slots":[-1]}]"#,
                "op 0 (delete): field `slots`",
            ),
            (
                r#"[{"op":"delete","slots":"some"}]"#,
                "op 0 (delete): field `slots`",
            ),
            (
                r#"[{"op":"delete","slot":[1]}]"#,
                "op 0 (delete): unknown field `slot`",
            ),
            (
                r#"[{"op":"prune","min_mass":2}]"#,
                "op 0 (prune): field `min_mass`",
            ),
            (
                r#"[{"op":"merge","slots":[0]}]"#,
                "op 0 (merge): field `from` is missing",
            ),
            (r#"[3]"#, "op 0: expected an object"),
            (r#"{"opz": []}"#, "unknown top-level field `opz`"),
            (r#"{"ops": 3}"#, "`ops` to be an array"),
            (r#"{"ops": ["#, "e.json: invalid JSON"),
        ];
        for (text, expected) in cases {
            let msg = err(text);
            assert!(msg.contains(expected), "`{msg}` lacks `{expected}`");
        }
    }

    #[test]
    fn apply_errors_name_the_op_and_leave_input_untouched() {
        let codes = sample(2);
        let e = apply_edits(
            &codes,
            &ops(r#"[{"op":"delete","slots":[1]},{"op":"translate","slots":[1],"by":[1,0,0]}]"#),
            "e.json",
        )
        .unwrap_err();
        let msg = format!("{e:#}");
        assert!(
            msg.starts_with("e.json: op 1 (translate): field `slots`: slot 1 does not exist"),
            "{msg}"
        );
    }

    #[test]
    fn edits_that_make_unwritable_codes_name_the_op() {
        let codes = sample(2);
        let msg = format!(
            "{:#}",
            apply_edits(
                &codes,
                &ops(r#"[{"op":"translate","slots":[1],"by":[1e39,0,0]}]"#),
                "e.json"
            )
            .unwrap_err()
        );
        assert!(msg.starts_with("e.json: op 0 (translate): slot 1"), "{msg}");
        let two = r#"[{"op":"translate","slots":"all","by":[1e308,0,0]},
                      {"op":"translate","slots":"all","by":[1e308,0,0]}]"#;
        let msg = format!(
            "{:#}",
            apply_edits(&codes, &ops(two), "e.json").unwrap_err()
        );
        assert!(msg.starts_with("e.json: op 0 (translate): slot 0"), "{msg}");
        // 14 doublings of 7 slots: 114,688, above the 100,000 a reader accepts; the 14th op
        // is named.
        let dup = vec![r#"{"op":"duplicate","slots":"all"}"#; 14].join(",");
        let msg = format!(
            "{:#}",
            apply_edits(&sample(7), &ops(&format!("[{dup}]")), "e.json").unwrap_err()
        );
        assert!(
            msg.starts_with("e.json: op 13 (duplicate): 114688 slots is more than the 100000"),
            "{msg}"
        );
    }

    #[test]
    fn rotation_about_huge_and_tiny_axes_still_turns() {
        let codes = sample(2);
        for axis in ["[0,0,1e200]", "[0,0,1e-200]", "[0,0,1]"] {
            let text = format!(r#"[{{"op":"rotate","slots":[1],"axis":{axis},"degrees":90}}]"#);
            let edited = apply_edits(&codes, &ops(&text), "e.json").unwrap();
            assert!(
                (origin(&edited, 1) - DVec3::new(0.0, 1.0, 0.0)).length() < 1e-12,
                "{axis}: {:?}",
                origin(&edited, 1)
            );
        }
        assert!(
            err(r#"[{"op":"rotate","slots":[1],"axis":[0,0,0],"degrees":9}]"#)
                .contains("must not be zero")
        );
    }

    #[test]
    fn inspect_norms_of_huge_finite_latents_are_finite() {
        let mut codes = sample(1);
        codes.slots[0].latent = vec![3e30, -3e30, 3e30, 4e30];
        let norm = inspect(&codes)["slots"][0]["latent_norm"].as_f64().unwrap();
        let expected = (3.0f64 * 9e60 + 16e60).sqrt();
        assert!((norm / expected - 1.0).abs() < 1e-6, "{norm}");
        assert_eq!(scaled_norm(&[0.0, 0.0]), 0.0);
        assert!((scaled_norm(&[3.0, 4.0]) - 5.0).abs() < 1e-12);
    }

    #[test]
    fn merge_and_background_from_files() {
        let dir = tempfile::tempdir().unwrap();
        let other_path = dir.path().join("other.codes");
        let mut other = sample(3);
        other.background = vec![9.0; 4];
        other.slots[2].source.clear();
        std::fs::write(&other_path, other.to_bytes().unwrap()).unwrap();
        let p = other_path.to_str().unwrap();
        let text = format!(
            r#"[{{"op":"merge","from":"{p}","slots":[0,2]}},{{"op":"background","from":"{p}"}}]"#
        );
        let e = apply_edits(&sample(1), &ops(&text), "e").unwrap();
        assert_eq!(e.slots.len(), 3);
        assert_eq!(e.slots[1], other.slots[0]);
        assert_eq!(e.slots[2].source, format!("{p}#2"));
        assert_eq!(e.background, vec![9.0; 4]);
        // Another model's codes are refused.
        other.model = "someone-else".into();
        std::fs::write(&other_path, other.to_bytes().unwrap()).unwrap();
        let msg = format!(
            "{:#}",
            apply_edits(&sample(1), &ops(&text), "e").unwrap_err()
        );
        assert!(
            msg.contains("op 0 (merge)") && msg.contains("someone-else"),
            "{msg}"
        );
    }
}
