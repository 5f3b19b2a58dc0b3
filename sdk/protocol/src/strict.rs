//! Strict decoding of the two MessagePack families the specification keeps apart: a text field
//! takes only `str`, a byte field only `bin` (docs/PROTOCOL.md §5). The stock serde visitors
//! accept either for both (a `String` from UTF-8 `bin`, bytes from `str` or an array of
//! integers); a peer that relies on that would break against any other conforming decoder, so
//! this one refuses it with a `bad_frame` naming the expected type.

use std::collections::BTreeMap;
use std::fmt;

use serde::de::{Deserializer, Error, MapAccess, Visitor};
use serde::{Deserialize, Serializer};

/// A text field: MessagePack `str` only. Use as `#[serde(deserialize_with = "strict::text")]`.
pub fn text<'de, D: Deserializer<'de>>(deserializer: D) -> Result<String, D::Error> {
    deserializer.deserialize_string(TextVisitor)
}

struct TextVisitor;

impl Visitor<'_> for TextVisitor {
    type Value = String;

    fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("a MessagePack str")
    }

    fn visit_str<E: Error>(self, v: &str) -> Result<String, E> {
        Ok(v.to_owned())
    }

    fn visit_string<E: Error>(self, v: String) -> Result<String, E> {
        Ok(v)
    }
}

/// A map with text keys and `f64` values (horizon parameters): keys are `str` only.
pub fn text_keyed_f64<'de, D: Deserializer<'de>>(
    deserializer: D,
) -> Result<BTreeMap<String, f64>, D::Error> {
    struct Key(String);
    impl<'de> Deserialize<'de> for Key {
        fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Key, D::Error> {
            text(deserializer).map(Key)
        }
    }
    struct MapVisitor;
    impl<'de> Visitor<'de> for MapVisitor {
        type Value = BTreeMap<String, f64>;

        fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
            f.write_str("a map of str keys to numbers")
        }

        fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Self::Value, A::Error> {
            let mut out = BTreeMap::new();
            while let Some((Key(key), value)) = map.next_entry::<Key, f64>()? {
                out.insert(key, value);
            }
            Ok(out)
        }
    }
    deserializer.deserialize_map(MapVisitor)
}

/// A byte field: MessagePack `bin` only. Use as `#[serde(with = "strict::bin")]`.
pub mod bin {
    use super::*;

    /// Writes `bytes` as MessagePack `bin`.
    pub fn serialize<S: Serializer>(bytes: &[u8], serializer: S) -> Result<S::Ok, S::Error> {
        serializer.serialize_bytes(bytes)
    }

    /// Reads MessagePack `bin`; refuses `str` and arrays.
    pub fn deserialize<'de, D: Deserializer<'de>>(deserializer: D) -> Result<Vec<u8>, D::Error> {
        deserializer.deserialize_byte_buf(BinVisitor)
    }

    struct BinVisitor;

    impl Visitor<'_> for BinVisitor {
        type Value = Vec<u8>;

        fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
            f.write_str("a MessagePack bin")
        }

        fn visit_bytes<E: Error>(self, v: &[u8]) -> Result<Vec<u8>, E> {
            Ok(v.to_vec())
        }

        fn visit_byte_buf<E: Error>(self, v: Vec<u8>) -> Result<Vec<u8>, E> {
            Ok(v)
        }
    }
}

/// An enumeration field (`dtype`, `outcome`, `code`, an image's `encoding`): a MessagePack `str`
/// naming a variant, nothing else. serde's derived enum visitor would also take a variant's
/// index as an integer (`"dtype": 0` as `f32`), and rmp-serde a one-entry map or array around
/// the name; an unknown name is refused either way (`bad_frame`, listing the names).
pub fn name<'de, D: Deserializer<'de>, T: serde::de::DeserializeOwned>(
    deserializer: D,
) -> Result<T, D::Error> {
    use serde::de::IntoDeserializer;
    let name = text(deserializer)?;
    T::deserialize(name.into_deserializer())
}

/// An optional enumeration field: absent, `nil` or a MessagePack `str` naming a variant (see
/// [`name`]).
pub fn opt_name<'de, D: Deserializer<'de>, T: serde::de::DeserializeOwned>(
    deserializer: D,
) -> Result<Option<T>, D::Error> {
    use serde::de::IntoDeserializer;
    match Option::<Text>::deserialize(deserializer)? {
        None => Ok(None),
        Some(Text(name)) => T::deserialize(name.into_deserializer()).map(Some),
    }
}

/// A `str`-only string as a deserializable value (for optional fields).
struct Text(String);

impl<'de> Deserialize<'de> for Text {
    fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Text, D::Error> {
        text(deserializer).map(Text)
    }
}

/// An optional text field: absent, `nil` or a MessagePack `str`.
pub fn opt_text<'de, D: Deserializer<'de>>(deserializer: D) -> Result<Option<String>, D::Error> {
    Ok(Option::<Text>::deserialize(deserializer)?.map(|Text(text)| text))
}

/// An optional byte field: absent, `nil` or MessagePack `bin`.
pub fn opt_bin<'de, D: Deserializer<'de>>(deserializer: D) -> Result<Option<Vec<u8>>, D::Error> {
    struct Bin(Vec<u8>);
    impl<'de> Deserialize<'de> for Bin {
        fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<Bin, D::Error> {
            bin::deserialize(deserializer).map(Bin)
        }
    }
    Ok(Option::<Bin>::deserialize(deserializer)?.map(|Bin(bytes)| bytes))
}

#[cfg(test)]
mod tests {
    use rmpv::Value;

    use serde::Deserialize;

    use super::super::codec::decode_body;
    use super::super::messages::{Hello, MessageKind, Submit};

    fn encode(value: &Value) -> Vec<u8> {
        let mut out = Vec::new();
        rmpv::encode::write_value(&mut out, value).unwrap();
        out
    }

    fn map(entries: Vec<(&str, Value)>) -> Value {
        Value::Map(
            entries
                .into_iter()
                .map(|(k, v)| (Value::from(k), v))
                .collect(),
        )
    }

    fn hello(token: Value) -> Vec<u8> {
        encode(&map(vec![
            ("protocol", Value::from(1)),
            ("token", token),
            ("client", Value::from("c")),
        ]))
    }

    #[test]
    fn a_token_is_a_str_not_a_bin() {
        let ok: Hello = decode_body(MessageKind::Hello, &hello(Value::from("t0k"))).unwrap();
        assert_eq!(ok.token, "t0k");
        let error =
            decode_body::<Hello>(MessageKind::Hello, &hello(Value::Binary(b"t0k".to_vec())))
                .unwrap_err()
                .to_string();
        assert!(error.contains("expected a MessagePack str"), "{error}");
    }

    fn submit(state_data: Value, params: Value) -> Vec<u8> {
        encode(&map(vec![
            ("task", Value::from(1)),
            ("round", Value::from(0)),
            ("sent_at_us", Value::from(10)),
            (
                "observation",
                map(vec![
                    ("captured_at_us", Value::from(5)),
                    (
                        "state",
                        map(vec![
                            ("dtype", Value::from("u8")),
                            ("shape", Value::Array(vec![Value::from(2)])),
                            ("data", state_data),
                        ]),
                    ),
                    ("images", Value::Array(Vec::new())),
                    ("instruction", Value::from("go")),
                ]),
            ),
            (
                "horizon",
                map(vec![("policy", Value::from("static")), ("params", params)]),
            ),
        ]))
    }

    #[test]
    fn tensor_data_is_a_bin_not_a_str_or_an_array() {
        let params = || Value::Map(vec![(Value::from("h"), Value::from(4.0))]);
        let ok: Submit = decode_body(
            MessageKind::Submit,
            &submit(Value::Binary(vec![1, 2]), params()),
        )
        .unwrap();
        assert_eq!(ok.observation.state.data, vec![1, 2]);
        assert_eq!(ok.horizon.unwrap().params["h"], 4.0);
        for lenient in [
            Value::from("ab"),
            Value::Array(vec![Value::from(1), Value::from(2)]),
        ] {
            let error = decode_body::<Submit>(MessageKind::Submit, &submit(lenient, params()))
                .unwrap_err()
                .to_string();
            assert!(error.contains("expected a MessagePack bin"), "{error}");
        }
    }

    #[test]
    fn enumerations_are_names_not_indices_or_wrappers() {
        let state = |dtype: Value| {
            let mut body = submit(Value::Binary(vec![1, 2]), Value::Map(Vec::new()));
            let mut value = rmpv::decode::read_value(&mut &body[..]).unwrap();
            if let Value::Map(fields) = &mut value
                && let Some((_, Value::Map(observation))) = fields
                    .iter_mut()
                    .find(|(k, _)| k.as_str() == Some("observation"))
                && let Some((_, Value::Map(tensor))) = observation
                    .iter_mut()
                    .find(|(k, _)| k.as_str() == Some("state"))
                && let Some((_, slot)) =
                    tensor.iter_mut().find(|(k, _)| k.as_str() == Some("dtype"))
            {
                *slot = dtype;
            }
            body.clear();
            rmpv::encode::write_value(&mut body, &value).unwrap();
            decode_body::<Submit>(MessageKind::Submit, &body).map_err(|e| e.to_string())
        };
        assert!(state(Value::from("u8")).is_ok());
        for lenient in [
            Value::from(3),
            Value::Array(vec![Value::from("u8")]),
            Value::Map(vec![(Value::from("u8"), Value::Nil)]),
            Value::Binary(b"u8".to_vec()),
        ] {
            let error = state(lenient.clone()).unwrap_err();
            assert!(
                error.contains("expected a MessagePack str"),
                "{lenient}: {error}"
            );
        }
        let error = state(Value::from("u9")).unwrap_err();
        assert!(error.contains("unknown variant `u9`"), "{error}");
    }

    #[test]
    fn image_encodings_are_names() {
        use super::super::messages::ImagePayload;
        let payload = |encoding: Value, data: Value| {
            let body = encode(&map(vec![("encoding", encoding), ("data", data)]));
            let mut de = rmp_serde::Deserializer::from_read_ref(&body[..]);
            ImagePayload::deserialize(&mut de).map_err(|e| e.to_string())
        };
        assert_eq!(
            payload(Value::from("png"), Value::Binary(vec![7])).unwrap(),
            ImagePayload::Png { data: vec![7] }
        );
        for lenient in [Value::from(1), Value::Binary(b"png".to_vec())] {
            let error = payload(lenient.clone(), Value::Binary(vec![7])).unwrap_err();
            assert!(
                error.contains("expected a MessagePack str"),
                "{lenient}: {error}"
            );
        }
        let error = payload(Value::from("gif"), Value::Binary(vec![7])).unwrap_err();
        assert!(error.contains("unknown variant `gif`"), "{error}");
        let error = payload(Value::from("jpeg"), Value::from("not bytes")).unwrap_err();
        assert!(error.contains("expected a MessagePack bin"), "{error}");
        let error = payload(Value::from("raw"), Value::Binary(vec![7])).unwrap_err();
        assert!(error.contains("missing field `tensor`"), "{error}");
    }

    #[test]
    fn map_keys_are_strs_everywhere() {
        // An integer key would otherwise be read as the field's index (0 = `protocol`).
        let body = encode(&Value::Map(vec![
            (Value::from(0), Value::from(1)),
            (Value::from("token"), Value::from("t")),
            (Value::from("client"), Value::from("c")),
        ]));
        let error = decode_body::<Hello>(MessageKind::Hello, &body)
            .unwrap_err()
            .to_string();
        assert!(error.contains("map key"), "{error}");
        let body = encode(&Value::Map(vec![
            (Value::Binary(b"protocol".to_vec()), Value::from(1)),
            (Value::from("token"), Value::from("t")),
            (Value::from("client"), Value::from("c")),
        ]));
        assert!(decode_body::<Hello>(MessageKind::Hello, &body).is_err());
        // Unknown keys with str names are ignored, as the specification says.
        let body = encode(&map(vec![
            ("protocol", Value::from(1)),
            ("token", Value::from("t")),
            ("client", Value::from("c")),
            ("future_field", Value::Array(vec![Value::from(1)])),
        ]));
        assert!(decode_body::<Hello>(MessageKind::Hello, &body).is_ok());
    }

    #[test]
    fn parameter_names_are_strs() {
        let bin_key = Value::Map(vec![(Value::Binary(b"h".to_vec()), Value::from(4.0))]);
        let error = decode_body::<Submit>(
            MessageKind::Submit,
            &submit(Value::Binary(vec![1, 2]), bin_key),
        )
        .unwrap_err()
        .to_string();
        assert!(error.contains("expected a MessagePack str"), "{error}");
    }
}
