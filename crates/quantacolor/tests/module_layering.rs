//! The library's top-level modules import each other without cycles (docs/architecture.md,
//! "Module layering": lower modules never import higher ones). Reads the sources as text: every
//! `crate::name` outside comments and `#[cfg(test)]` modules is an edge from the file's top-level
//! module to `name`.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

type Graph = BTreeMap<String, BTreeSet<String>>;

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).expect("source folder is readable") {
        let path = entry.expect("directory entry").path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") && !is_test_module(&path) {
            out.push(path);
        }
    }
}

/// Files that hold only `#[cfg(test)]` modules (declared `#[cfg(test)] mod tests;` or
/// `mod test_oracle;` by their parents): their imports are not edges of the library.
fn is_test_module(path: &Path) -> bool {
    path.file_stem()
        .is_some_and(|s| s == "tests" || s == "test_oracle")
}

/// The source without line comments and without everything from the first `#[cfg(test)]`.
fn code_of(text: &str) -> String {
    let text = text.split("#[cfg(test)]").next().unwrap_or("");
    text.lines()
        .map(|l| l.split("//").next().unwrap_or(""))
        .collect::<Vec<_>>()
        .join("\n")
}

/// The names `x` of every `crate::x` in `code`.
fn crate_paths(code: &str) -> BTreeSet<String> {
    code.match_indices("crate::")
        .filter(|(i, _)| {
            // Not part of a longer identifier (e.g. `mycrate::`).
            code[..*i]
                .chars()
                .next_back()
                .is_none_or(|c| !(c.is_alphanumeric() || c == '_'))
        })
        .map(|(i, m)| {
            code[i + m.len()..]
                .chars()
                .take_while(|c| c.is_alphanumeric() || *c == '_')
                .collect::<String>()
        })
        .filter(|name| !name.is_empty())
        .collect()
}

/// The top-level module graph of the library's sources.
fn module_graph(src: &Path) -> Graph {
    let mut files = Vec::new();
    rust_files(src, &mut files);
    let mut graph = Graph::new();
    for file in files {
        let rel = file.strip_prefix(src).expect("under src");
        let first = rel
            .components()
            .next()
            .expect("non-empty path")
            .as_os_str()
            .to_string_lossy()
            .trim_end_matches(".rs")
            .to_string();
        if first == "lib" || first == "main" {
            continue;
        }
        let text = std::fs::read_to_string(&file).expect("source is readable");
        let targets = graph.entry(first.clone()).or_default();
        for target in crate_paths(&code_of(&text)) {
            if target != first {
                targets.insert(target);
            }
        }
    }
    graph
}

/// A cycle of `graph` as the list of its modules (first repeated at the end), if any.
fn find_cycle(graph: &Graph) -> Option<Vec<String>> {
    // 0: unvisited, 1: on the current path, 2: done.
    fn visit(
        node: &str,
        graph: &Graph,
        state: &mut BTreeMap<String, u8>,
        path: &mut Vec<String>,
    ) -> Option<Vec<String>> {
        state.insert(node.to_string(), 1);
        path.push(node.to_string());
        for next in graph.get(node).into_iter().flatten() {
            match state.get(next.as_str()).copied().unwrap_or(0) {
                1 => {
                    let start = path.iter().position(|n| n == next).expect("on the path");
                    let mut cycle = path[start..].to_vec();
                    cycle.push(next.clone());
                    return Some(cycle);
                }
                0 => {
                    if let Some(cycle) = visit(next, graph, state, path) {
                        return Some(cycle);
                    }
                }
                _ => {}
            }
        }
        path.pop();
        state.insert(node.to_string(), 2);
        None
    }
    let mut state = BTreeMap::new();
    for node in graph.keys() {
        if state.get(node.as_str()).copied().unwrap_or(0) == 0 {
            if let Some(cycle) = visit(node, graph, &mut state, &mut Vec::new()) {
                return Some(cycle);
            }
        }
    }
    None
}

#[test]
fn top_level_modules_import_each_other_without_cycles() {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let graph = module_graph(&src);
    // The reader sees the modules and their imports (a reader that saw nothing finds no cycle).
    assert!(graph.len() >= 15, "modules read: {:?}", graph.keys());
    assert!(graph["burst"].contains("align") && graph["burst"].contains("merge"));
    assert!(
        graph["model"].iter().all(|m| m == "error"),
        "{:?}",
        graph["model"]
    );
    if let Some(cycle) = find_cycle(&graph) {
        panic!("import cycle between modules: {}", cycle.join(" -> "));
    }
}

#[test]
fn the_cycle_finder_finds_a_cycle_and_the_reader_skips_comments_and_tests() {
    let mut graph = Graph::new();
    for (a, b) in [("merge", "model"), ("align", "merge"), ("model", "align")] {
        graph.entry(a.into()).or_default().insert(b.into());
    }
    let cycle = find_cycle(&graph).expect("a cycle");
    assert_eq!(cycle.first(), cycle.last());
    assert_eq!(cycle.len(), 4);
    graph.get_mut("model").unwrap().clear();
    assert_eq!(find_cycle(&graph), None);

    let code = code_of(
        "use crate::model::x; // crate::align\nfn f() { crate::filters::g(); }\n\
         #[cfg(test)]\nmod tests { use crate::burst; }",
    );
    let names: Vec<String> = crate_paths(&code).into_iter().collect();
    assert_eq!(names, ["filters", "model"]);
}
