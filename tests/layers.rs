//! The layering of `src/` (docs/DESIGN.md §3), read from the code's own `crate::…` and `super::…`
//! paths: every arrow between top-level modules points down the floors below, and inside a module
//! the files import each other without a circle.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// The floors, bottom first. A module may use only modules on floors below its own.
const FLOORS: &[&[&str]] = &[
    &["so3", "encoding", "schedule", "backend", "viz"],
    &["cad", "net"],
    &["data"],
    &["experts"],
    &["bundle"],
    &["engine"],
    &["train", "serve"],
    &["client"],
    &["bench"],
];

fn floor_of(module: &str) -> usize {
    FLOORS
        .iter()
        .position(|f| f.contains(&module))
        .unwrap_or_else(|| panic!("module `{module}` is on no floor: add it to FLOORS"))
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

/// The file's module path below `src/`: `["net", "fused"]`, `["net"]` for `net/mod.rs`.
fn module_of(rel: &Path) -> Vec<String> {
    let mut parts: Vec<String> = rel
        .with_extension("")
        .iter()
        .map(|p| p.to_string_lossy().into_owned())
        .collect();
    if parts.last().is_some_and(|p| p == "mod") {
        parts.pop();
    }
    parts
}

/// The code without `//` comments (doc links are not imports). String literals that hold `//`
/// are rare enough in this crate not to matter for paths.
fn code_of(text: &str) -> String {
    text.lines()
        .map(|l| l.find("//").map_or(l, |i| &l[..i]))
        .collect::<Vec<_>>()
        .join("\n")
}

fn ident(s: &str) -> &str {
    let end = s
        .find(|c: char| !(c.is_ascii_alphanumeric() || c == '_'))
        .unwrap_or(s.len());
    &s[..end]
}

/// The first two segments of every path after `prefix` (`crate::a::b`, and each item of
/// `crate::{a::b, c}`).
fn paths_after(code: &str, prefix: &str) -> Vec<(String, Option<String>)> {
    let mut out = Vec::new();
    for (at, _) in code.match_indices(prefix) {
        let rest = &code[at + prefix.len()..];
        if let Some(group) = rest.strip_prefix('{') {
            let mut depth = 1;
            let end = group
                .char_indices()
                .find(|&(_, c)| {
                    depth += match c {
                        '{' => 1,
                        '}' => -1,
                        _ => 0,
                    };
                    depth == 0
                })
                .map_or(group.len(), |(i, _)| i);
            let mut depth = 0;
            let mut item = String::new();
            let mut items = Vec::new();
            for c in group[..end].chars() {
                match c {
                    '{' => depth += 1,
                    '}' => depth -= 1,
                    ',' if depth == 0 => items.push(std::mem::take(&mut item)),
                    _ => {}
                }
                item.push(c);
            }
            items.push(item);
            for item in items {
                let item = item.trim_start_matches(',').trim();
                let first = ident(item);
                if !first.is_empty() {
                    let second = item[first.len()..].strip_prefix("::").map(ident);
                    out.push((first.to_string(), second.map(str::to_string)));
                }
            }
        } else {
            let first = ident(rest);
            let second = rest[first.len()..].strip_prefix("::").map(ident);
            out.push((first.to_string(), second.map(str::to_string)));
        }
    }
    out
}

struct Graph {
    /// Arrows between top-level modules, each with a file that draws it.
    modules: BTreeMap<(String, String), String>,
    /// Arrows between the files of one module (`net/fused` → `net/tiles`).
    files: BTreeMap<String, BTreeSet<String>>,
}

fn import_graph() -> Graph {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = Vec::new();
    rust_files(&src, &mut files);
    let mut graph = Graph {
        modules: BTreeMap::new(),
        files: BTreeMap::new(),
    };
    for path in files {
        let rel = path.strip_prefix(&src).unwrap();
        if rel.starts_with("bin") || rel == Path::new("lib.rs") {
            continue;
        }
        let me = module_of(rel);
        let code = code_of(&std::fs::read_to_string(&path).unwrap());
        let sibling = |name: &str| src.join(&me[0]).join(format!("{name}.rs")).exists();
        let mut file_arrow = |to: &str| {
            if me.len() == 2 && to != me[1] && sibling(to) {
                graph
                    .files
                    .entry(me.join("/"))
                    .or_default()
                    .insert(format!("{}/{to}", me[0]));
            }
        };
        for (first, second) in paths_after(&code, "crate::") {
            if first != me[0] {
                graph
                    .modules
                    .entry((me[0].clone(), first))
                    .or_insert_with(|| rel.display().to_string());
            } else if let Some(second) = second {
                file_arrow(&second);
            }
        }
        for (first, _) in paths_after(&code, "super::") {
            file_arrow(&first);
        }
    }
    graph
}

#[test]
fn every_arrow_between_modules_points_down() {
    let graph = import_graph();
    assert!(
        graph.modules.len() > 20,
        "the scan found too few arrows: {:?}",
        graph.modules
    );
    let up: Vec<String> = graph
        .modules
        .iter()
        .filter(|((from, to), _)| floor_of(from) <= floor_of(to))
        .map(|((from, to), file)| format!("{from} → {to} (src/{file})"))
        .collect();
    assert!(up.is_empty(), "arrows up or sideways: {up:#?}");
}

#[test]
fn the_files_of_a_module_import_each_other_without_a_circle() {
    let graph = import_graph();
    assert!(
        graph.files.contains_key("net/fused"),
        "the scan missed net/fused's imports"
    );
    // Depth-first search for a back edge.
    fn visit(
        node: &str,
        edges: &BTreeMap<String, BTreeSet<String>>,
        state: &mut BTreeMap<String, u8>,
        stack: &mut Vec<String>,
    ) -> Option<Vec<String>> {
        state.insert(node.to_string(), 1);
        stack.push(node.to_string());
        for next in edges.get(node).into_iter().flatten() {
            match state.get(next.as_str()) {
                Some(1) => {
                    let from = stack.iter().position(|n| n == next).unwrap();
                    return Some(stack[from..].to_vec());
                }
                Some(_) => {}
                None => {
                    if let Some(circle) = visit(next, edges, state, stack) {
                        return Some(circle);
                    }
                }
            }
        }
        stack.pop();
        state.insert(node.to_string(), 2);
        None
    }
    let mut state = BTreeMap::new();
    for node in graph.files.keys() {
        if !state.contains_key(node.as_str())
            && let Some(circle) = visit(node, &graph.files, &mut state, &mut Vec::new())
        {
            panic!("an import circle: {}", circle.join(" → "));
        }
    }
}

#[test]
fn the_scan_reads_grouped_and_nested_paths() {
    let code =
        "use crate::{net::{Dense, Rows}, so3::grid::Grid};\nlet x = crate::cad::mesh::load();";
    let found = paths_after(code, "crate::");
    let firsts: Vec<&str> = found.iter().map(|(f, _)| f.as_str()).collect();
    assert_eq!(firsts, ["net", "so3", "cad"]);
    assert_eq!(found[1].1.as_deref(), Some("grid"));
    assert_eq!(code_of("a // crate::x\nb"), "a \nb");
}

/// `text` with every comment, string and character literal blanked (newlines kept), so that
/// braces count as code.
fn blanked(text: &str) -> String {
    let chars: Vec<char> = text.chars().collect();
    let mut out = String::with_capacity(text.len());
    let mut i = 0;
    let keep = |c: char| if c == '\n' { '\n' } else { ' ' };
    while i < chars.len() {
        let c = chars[i];
        let next = chars.get(i + 1).copied();
        if c == '/' && next == Some('/') {
            while i < chars.len() && chars[i] != '\n' {
                out.push(' ');
                i += 1;
            }
        } else if c == '/' && next == Some('*') {
            let mut depth = 0;
            while i < chars.len() {
                if chars[i] == '/' && chars.get(i + 1) == Some(&'*') {
                    depth += 1;
                } else if chars[i] == '*' && chars.get(i + 1) == Some(&'/') {
                    depth -= 1;
                    out.push_str("  ");
                    i += 2;
                    if depth == 0 {
                        break;
                    }
                    continue;
                }
                out.push(keep(chars[i]));
                i += 1;
            }
        } else if c == 'r' && (next == Some('"') || next == Some('#')) && {
            let hashes = chars[i + 1..].iter().take_while(|&&h| h == '#').count();
            chars.get(i + 1 + hashes) == Some(&'"')
        } {
            // A raw string: r#"…"# with as many hashes to close as to open.
            let hashes = chars[i + 1..].iter().take_while(|&&h| h == '#').count();
            i += 2 + hashes;
            out.push_str(&" ".repeat(2 + hashes));
            while i < chars.len() {
                if chars[i] == '"' && chars[i + 1..].iter().take(hashes).all(|&h| h == '#') {
                    out.push_str(&" ".repeat(1 + hashes));
                    i += 1 + hashes;
                    break;
                }
                out.push(keep(chars[i]));
                i += 1;
            }
        } else if c == '"' {
            out.push(' ');
            i += 1;
            while i < chars.len() && chars[i] != '"' {
                if chars[i] == '\\' {
                    out.push(' ');
                    i += 1;
                }
                if i < chars.len() {
                    out.push(keep(chars[i]));
                    i += 1;
                }
            }
            out.push(' ');
            i += 1;
        } else if c == '\''
            && (chars.get(i + 2) == Some(&'\'')
                || (next == Some('\\') && chars.get(i + 3) == Some(&'\'')))
        {
            // A character literal ('{', '\n'); a lifetime ('a) has no closing quote.
            let len = if next == Some('\\') { 4 } else { 3 };
            out.push_str(&" ".repeat(len));
            i += len;
        } else {
            out.push(c);
            i += 1;
        }
    }
    out
}

/// Every function of `text` longer than `most` lines: `(name, first line, lines)`.
fn long_functions(text: &str, most: usize) -> Vec<(String, usize, usize)> {
    let code = blanked(text);
    let lines: Vec<&str> = code.lines().collect();
    let mut long = Vec::new();
    for (start, line) in lines.iter().enumerate() {
        let words: Vec<&str> = line.split_whitespace().collect();
        let Some(at) = words.iter().position(|w| *w == "fn") else {
            continue;
        };
        let Some(name) = words.get(at + 1).map(|w| ident(w)) else {
            continue;
        };
        if name.is_empty() {
            continue;
        }
        // From the signature to the brace that closes the body (none: a declaration).
        let mut depth = 0i64;
        let mut opened = false;
        for (end, l) in lines.iter().enumerate().skip(start) {
            for ch in l.chars() {
                match ch {
                    '{' => {
                        depth += 1;
                        opened = true;
                    }
                    '}' => depth -= 1,
                    ';' if !opened && depth == 0 => break,
                    _ => {}
                }
            }
            if (opened && depth == 0) || (!opened && l.trim_end().ends_with(';')) {
                if opened && end - start + 1 > most {
                    long.push((name.to_string(), start + 1, end - start + 1));
                }
                break;
            }
        }
    }
    long
}

/// No function in `src/`, `tests/`, `examples/` or `benches/` is over 100 lines
/// (docs/DESIGN.md §3): long ones are split into named steps.
#[test]
fn no_function_is_over_100_lines() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut files = Vec::new();
    for dir in ["src", "tests", "examples", "benches"] {
        if root.join(dir).is_dir() {
            rust_files(&root.join(dir), &mut files);
        }
    }
    let mut long = Vec::new();
    for file in &files {
        let text = std::fs::read_to_string(file).unwrap();
        for (name, line, lines) in long_functions(&text, 100) {
            let rel = file.strip_prefix(root).unwrap().display();
            long.push(format!("{rel}:{line} {name} ({lines} lines)"));
        }
    }
    assert!(
        long.is_empty(),
        "functions over 100 lines:\n{}",
        long.join("\n")
    );
}

#[test]
fn the_length_scan_skips_braces_in_strings_and_counts_bodies() {
    let body: String = (0..101)
        .map(|i| format!("    let x{i} = \"}}\";\n"))
        .collect();
    let text = format!("fn long() {{\n{body}}}\nfn short() {{ '{{'; }}\nfn decl();\n");
    let long = long_functions(&text, 100);
    assert_eq!(long, vec![("long".to_string(), 1, 103)]);
    assert!(long_functions(&text, 103).is_empty());
}
