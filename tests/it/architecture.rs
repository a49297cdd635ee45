//! The layering rules of ARCHITECTURE.md, checked over the source tree: no import cycle between
//! files of a crate, no cycle between core's top-level modules, the app never reaching into the
//! CLI, core never importing a front end. Reads `use` lines and `crate::`/`super::` paths; a
//! folder's `pub use` re-exports are its façade, not an import, and a path through a façade is
//! followed to the file that defines the item where the re-export names it.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// One module file: its path in the crate (`["dataset", "preflight"]`) and its text, comments and
/// the trailing `#[cfg(test)] mod tests` removed (tests may import anything).
struct ModuleFile {
    module: Vec<String>,
    file: PathBuf,
    code: String,
}

/// The module files of one crate, keyed by module path.
struct Crate {
    name: String,
    files: BTreeMap<Vec<String>, ModuleFile>,
}

fn strip_comments(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for line in text.lines() {
        // Good enough for this tree: no `//` inside a string literal on a line with a path.
        let code = match line.find("//") {
            Some(at) => &line[..at],
            None => line,
        };
        out.push_str(code);
        out.push('\n');
    }
    out
}

fn without_test_module(text: &str) -> String {
    let lines: Vec<&str> = text.lines().collect();
    for i in 0..lines.len() {
        if lines[i].trim() == "#[cfg(test)]"
            && lines.get(i + 1).is_some_and(|next| next.trim_start().starts_with("mod "))
        {
            return lines[..i].join("\n");
        }
    }
    text.to_string()
}

fn load_crate(name: &str, src: &Path, root_file: &str) -> Crate {
    let mut files = BTreeMap::new();
    let mut stack = vec![src.to_path_buf()];
    while let Some(dir) = stack.pop() {
        for entry in std::fs::read_dir(&dir).expect("read a source folder") {
            let path = entry.expect("a folder entry").path();
            if path.is_dir() {
                stack.push(path);
                continue;
            }
            if path.extension().and_then(|e| e.to_str()) != Some("rs") {
                continue;
            }
            let rel = path.strip_prefix(src).unwrap();
            let mut module: Vec<String> =
                rel.with_extension("").components().map(|c| c.as_os_str().to_string_lossy().into_owned()).collect();
            let last = module.last().cloned().unwrap_or_default();
            if module.len() == 1 && (last == "main" || last == "lib") {
                if last != root_file {
                    continue; // the binary's main.rs is its own crate
                }
                module.clear();
            } else if last == "mod" {
                module.pop();
            }
            let text = std::fs::read_to_string(&path).expect("read a source file");
            let code = without_test_module(&strip_comments(&text));
            files.insert(module.clone(), ModuleFile { module, file: path, code });
        }
    }
    Crate { name: name.to_string(), files }
}

fn is_ident_char(c: char) -> bool {
    c.is_ascii_alphanumeric() || c == '_'
}

/// Parses a path starting at `text` (just after a leading `crate::`, `super::` or a child's
/// name), expanding `{a, b::c}` groups, into the full paths it names.
fn parse_paths(text: &str) -> Vec<Vec<String>> {
    fn parse(chars: &[char], pos: &mut usize, prefix: Vec<String>, out: &mut Vec<Vec<String>>) {
        let mut path = prefix;
        loop {
            while *pos < chars.len() && chars[*pos].is_whitespace() {
                *pos += 1;
            }
            if *pos < chars.len() && chars[*pos] == '{' {
                *pos += 1;
                loop {
                    parse(chars, pos, path.clone(), out);
                    while *pos < chars.len() && chars[*pos].is_whitespace() {
                        *pos += 1;
                    }
                    if *pos < chars.len() && chars[*pos] == ',' {
                        *pos += 1;
                        continue;
                    }
                    if *pos < chars.len() && chars[*pos] == '}' {
                        *pos += 1;
                    }
                    return;
                }
            }
            let start = *pos;
            while *pos < chars.len() && is_ident_char(chars[*pos]) {
                *pos += 1;
            }
            if *pos == start {
                break;
            }
            path.push(chars[start..*pos].iter().collect());
            if chars.get(*pos) == Some(&':') && chars.get(*pos + 1) == Some(&':') {
                *pos += 2;
                continue;
            }
            break;
        }
        // `{ x, }` leaves an empty group member; a `self` member names the module itself.
        if path.last().is_some_and(|s| s == "self") {
            path.pop();
        }
        out.push(path);
    }
    let chars: Vec<char> = text.chars().take(2000).collect();
    let mut out = Vec::new();
    parse(&chars, &mut 0, Vec::new(), &mut out);
    out
}

/// Every path the file names that starts at the crate root, its parent, itself or a child
/// module, as absolute module paths, and whether each came from a `pub use` (a re-export).
fn referenced_paths(krate: &Crate, file: &ModuleFile) -> Vec<(Vec<String>, bool)> {
    let is_folder_module = {
        let name = file.file.file_name().unwrap().to_string_lossy();
        name == "mod.rs" || name == "lib.rs" || name == "main.rs"
    };
    // `super` of a file `a/b.rs` is `a`; of `a/b/mod.rs` also `a`; `self` is the module.
    let here = file.module.clone();
    let parent: Vec<String> = here[..here.len().saturating_sub(1)].to_vec();
    let children: BTreeSet<String> = krate
        .files
        .keys()
        .filter(|m| m.len() == here.len() + 1 && m[..here.len()] == here[..])
        .map(|m| m.last().unwrap().clone())
        .collect();
    let _ = is_folder_module;
    let code = &file.code;
    let bytes: Vec<char> = code.chars().collect();
    let mut out = Vec::new();
    let mut i = 0;
    while i < bytes.len() {
        if !is_ident_char(bytes[i]) || (i > 0 && (is_ident_char(bytes[i - 1]) || bytes[i - 1] == ':')) {
            i += 1;
            continue;
        }
        let mut j = i;
        while j < bytes.len() && is_ident_char(bytes[j]) {
            j += 1;
        }
        let word: String = bytes[i..j].iter().collect();
        let followed = bytes.get(j) == Some(&':') && bytes.get(j + 1) == Some(&':');
        let base = match word.as_str() {
            "crate" if followed => Some(Vec::new()),
            "super" if followed => Some(parent.clone()),
            "self" if followed => Some(here.clone()),
            w if followed && children.contains(w) => {
                let mut p = here.clone();
                p.push(w.to_string());
                Some(p)
            }
            _ => None,
        };
        if let Some(base) = base {
            // A re-export when the statement is `pub use` (or `pub(crate) use`).
            let line_start = code[..code.char_indices().nth(i).map(|(b, _)| b).unwrap_or(0)]
                .rfind(['\n', ';', '{'])
                .map(|b| b + 1)
                .unwrap_or(0);
            let stmt_head: String = code[line_start..].trim_start().chars().take(16).collect();
            let re_export = stmt_head.starts_with("pub use") || stmt_head.starts_with("pub(crate) use");
            let rest_start = if matches!(word.as_str(), "crate" | "super" | "self") { j + 2 } else { i };
            let rest: String = bytes[rest_start..].iter().take(2000).collect();
            let skip_first = !matches!(word.as_str(), "crate" | "super" | "self");
            for tail in parse_paths(&rest) {
                let mut path = base.clone();
                let tail = if skip_first { &tail[1..] } else { &tail[..] };
                path.extend(tail.iter().cloned());
                out.push((path, re_export));
            }
            j = rest_start;
        }
        i = j.max(i + 1);
    }
    out
}

/// The module file a path lands in: the longest prefix that is a module, followed through that
/// module's `pub use` re-exports when they name the item.
fn resolve(krate: &Crate, path: &[String], reexports: &BTreeMap<Vec<String>, Vec<String>>) -> Vec<String> {
    let mut path = path.to_vec();
    for _ in 0..8 {
        let mut k = path.len();
        while k > 0 && !krate.files.contains_key(&path[..k]) {
            k -= 1;
        }
        let module = path[..k].to_vec();
        if k < path.len()
            && let Some(target) = reexports.get(&path[..=k].to_vec())
        {
            let mut next = target.clone();
            next.extend(path[k + 1..].iter().cloned());
            if next != path {
                path = next;
                continue;
            }
        }
        return module;
    }
    path
}

/// File-level import graph of a crate: module -> modules it imports (re-exports excluded).
fn import_graph(krate: &Crate) -> BTreeMap<Vec<String>, BTreeSet<Vec<String>>> {
    // Re-exports: `module::Name` -> the path it stands for.
    let mut reexports = BTreeMap::new();
    let mut refs = BTreeMap::new();
    for (module, file) in &krate.files {
        let paths = referenced_paths(krate, file);
        for (path, re_export) in &paths {
            if *re_export && let Some(name) = path.last() {
                let mut key = module.clone();
                key.push(name.clone());
                if &key != path {
                    reexports.insert(key, path.clone());
                }
            }
        }
        refs.insert(module.clone(), paths);
    }
    let mut graph: BTreeMap<Vec<String>, BTreeSet<Vec<String>>> = BTreeMap::new();
    for (module, paths) in refs {
        let edges = graph.entry(module.clone()).or_default();
        for (path, re_export) in paths {
            if re_export {
                continue;
            }
            let target = resolve(krate, &path, &reexports);
            if target != module {
                edges.insert(target);
            }
        }
    }
    graph
}

/// Every cycle's strongly connected component (Tarjan), as sorted member lists.
fn cycles<N: Ord + Clone>(graph: &BTreeMap<N, BTreeSet<N>>) -> Vec<Vec<N>> {
    let nodes: Vec<N> = graph.keys().cloned().collect();
    let index_of: BTreeMap<N, usize> = nodes.iter().cloned().enumerate().map(|(i, n)| (n, i)).collect();
    let adj: Vec<Vec<usize>> =
        nodes.iter().map(|n| graph[n].iter().filter_map(|m| index_of.get(m).copied()).collect()).collect();
    let n = nodes.len();
    let (mut index, mut low, mut on_stack) = (vec![usize::MAX; n], vec![0; n], vec![false; n]);
    let (mut stack, mut next, mut out) = (Vec::new(), 0, Vec::new());
    fn visit(
        v: usize,
        adj: &[Vec<usize>],
        index: &mut [usize],
        low: &mut [usize],
        on_stack: &mut [bool],
        stack: &mut Vec<usize>,
        next: &mut usize,
        out: &mut Vec<Vec<usize>>,
    ) {
        index[v] = *next;
        low[v] = *next;
        *next += 1;
        stack.push(v);
        on_stack[v] = true;
        for &w in &adj[v] {
            if index[w] == usize::MAX {
                visit(w, adj, index, low, on_stack, stack, next, out);
                low[v] = low[v].min(low[w]);
            } else if on_stack[w] {
                low[v] = low[v].min(index[w]);
            }
        }
        if low[v] == index[v] {
            let mut component = Vec::new();
            loop {
                let w = stack.pop().unwrap();
                on_stack[w] = false;
                component.push(w);
                if w == v {
                    break;
                }
            }
            if component.len() > 1 {
                out.push(component);
            }
        }
    }
    let mut found = Vec::new();
    for v in 0..n {
        if index[v] == usize::MAX {
            visit(v, &adj, &mut index, &mut low, &mut on_stack, &mut stack, &mut next, &mut found);
        }
    }
    for component in found {
        let mut members: Vec<N> = component.into_iter().map(|i| nodes[i].clone()).collect();
        members.sort();
        out.push(members);
    }
    out
}

fn show(module: &[String]) -> String {
    if module.is_empty() { "(root)".into() } else { module.join("::") }
}

fn workspace() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn crates() -> Vec<Crate> {
    let root = workspace();
    vec![
        load_crate("umesh-core", &root.join("crates/umesh-core/src"), "lib"),
        load_crate("umesh-net", &root.join("crates/umesh-net/src"), "lib"),
        load_crate("umesh", &root.join("src"), "lib"),
        load_crate("umesh-workflow", &root.join("crates/umesh-workflow/src"), "lib"),
    ]
}

fn file_cycles(krate: &Crate) -> Vec<String> {
    cycles(&import_graph(krate))
        .into_iter()
        .map(|c| format!("{}: {}", krate.name, c.iter().map(|m| show(m)).collect::<Vec<_>>().join(" <-> ")))
        .collect()
}

/// Module cycles at every level: for each module with submodules, its children as one node
/// each (a child stands for everything under it), an edge where anything under one imports
/// anything under another.
fn module_cycles(krate: &Crate) -> Vec<String> {
    let graph = import_graph(krate);
    let mut parents: BTreeSet<Vec<String>> = BTreeSet::new();
    for m in krate.files.keys() {
        for len in 0..m.len() {
            parents.insert(m[..len].to_vec());
        }
    }
    let mut found = Vec::new();
    for parent in parents {
        let child_of =
            |m: &[String]| (m.len() > parent.len() && m.starts_with(&parent)).then(|| m[parent.len()].clone());
        let mut level: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
        for (from, targets) in &graph {
            let Some(a) = child_of(from) else { continue };
            level.entry(a.clone()).or_default();
            for to in targets {
                if let Some(b) = child_of(to)
                    && b != a
                {
                    level.entry(a.clone()).or_default().insert(b.clone());
                    level.entry(b).or_default();
                }
            }
        }
        for c in cycles(&level) {
            let full = |name: &String| show(&[parent.clone(), vec![name.clone()]].concat());
            found.push(format!("{}: modules {}", krate.name, c.iter().map(full).collect::<Vec<_>>().join(" <-> ")));
        }
    }
    found
}

#[test]
fn no_file_of_a_crate_imports_a_file_that_imports_it_back() {
    let mut found = Vec::new();
    for krate in crates() {
        assert!(krate.files.len() > 5, "{}: no source files found", krate.name);
        found.extend(file_cycles(&krate));
    }
    assert!(found.is_empty(), "import cycles between files:\n{}", found.join("\n"));
}

#[test]
fn no_module_of_any_crate_imports_a_sibling_that_imports_it_back() {
    let mut found = Vec::new();
    for krate in crates() {
        found.extend(module_cycles(&krate));
    }
    assert!(found.is_empty(), "import cycles between modules:\n{}", found.join("\n"));
}

#[test]
fn the_app_never_reaches_into_the_cli_and_the_network_holds_no_workflow() {
    let app = &crates()[2];
    let mut wrong = Vec::new();
    for (module, file) in &app.files {
        if module.first().map(String::as_str) == Some("app")
            && referenced_paths(app, file).iter().any(|(p, _)| p.first().map(String::as_str) == Some("cli"))
        {
            wrong.push(format!("{} imports crate::cli", file.file.display()));
        }
    }
    let net = &crates()[1];
    for name in ["patient", "report"] {
        if net.files.contains_key(&vec![name.to_string()]) {
            wrong.push(format!("umesh-net holds `{name}` (workflow code belongs in umesh-workflow)"));
        }
    }
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
}

/// ARCHITECTURE.md's rule for the app: a view (model, jobs, qa, ar) imports the shared state,
/// the set-up, the scan and the shell's services, never another view; views are imported by
/// the app's plugin list and view list (`app/views.rs`), the screenshot scenes and the CLI,
/// and the window's frame imports the model view only (the File menu opens organs and sessions).
#[test]
fn no_view_of_the_app_imports_another_view() {
    let app = &crates()[2];
    let views = ["model", "jobs", "qa", "ar"];
    let view_of = |m: &[String]| -> Option<String> {
        (m.len() >= 2 && m[0] == "app" && views.contains(&m[1].as_str())).then(|| m[1].clone())
    };
    let may_import = |m: &[String], view: &str| {
        m == ["app"]
            || m == ["app", "views"]
            || m == ["app", "screenshot"]
            || (m == ["app", "frame"] && view == "model")
            || m.first().map(String::as_str) == Some("cli")
    };
    let mut wrong = Vec::new();
    for (from, targets) in import_graph(app) {
        for to in targets {
            let Some(target_view) = view_of(&to) else { continue };
            let allowed = match view_of(&from) {
                Some(own) => own == target_view,
                None => may_import(&from, &target_view),
            };
            if !allowed {
                wrong.push(format!("{} imports {}", show(&from), show(&to)));
            }
        }
    }
    assert!(wrong.is_empty(), "imports across the app's views:\n{}", wrong.join("\n"));
}

/// The checker itself, on a made-up crate: a cycle through a `use` group and `super::` is found,
/// a façade's re-export is not an import.
#[test]
fn the_cycle_check_finds_a_cycle_added_through_a_use_group_and_super() {
    let make = |files: &[(&str, &str)]| Crate {
        name: "made-up".into(),
        files: files
            .iter()
            .map(|(path, code)| {
                let module: Vec<String> =
                    if path.is_empty() { Vec::new() } else { path.split('/').map(String::from).collect() };
                (
                    module.clone(),
                    ModuleFile {
                        module,
                        file: PathBuf::from(format!("{path}.rs")),
                        code: without_test_module(&strip_comments(code)),
                    },
                )
            })
            .collect(),
    };
    let acyclic = make(&[
        ("", "pub mod a;\npub mod b;\npub use a::Thing;\n"),
        ("a", "pub mod x;\npub use x::Deep;\npub struct Thing;\n"),
        ("a/x", "use super::Thing; // the parent's type\npub struct Deep;\n"),
        (
            "b",
            "use crate::{a::Deep, Thing};\nfn f() { crate::a::x::Deep; }\n#[cfg(test)]\nmod tests { use crate::b; }\n",
        ),
    ]);
    assert!(file_cycles(&acyclic).is_empty(), "{:?}", file_cycles(&acyclic));
    assert!(module_cycles(&acyclic).is_empty(), "{:?}", module_cycles(&acyclic));
    let cyclic = make(&[
        ("", "pub mod a;\npub mod b;\n"),
        ("a", "pub mod x;\n"),
        ("a/x", "use crate::{b::{self, Other}};\npub struct Deep;\n"),
        ("b", "pub struct Other;\nfn f() -> crate::a::x::Deep { todo!() }\n"),
    ]);
    let found = file_cycles(&cyclic);
    assert_eq!(found, vec!["made-up: a::x <-> b".to_string()], "{found:?}");
    assert_eq!(module_cycles(&cyclic), vec!["made-up: modules a <-> b".to_string()]);
}

/// Every source or script file that README.md, ARCHITECTURE.md and docs/ name in backticks exists (as
/// a path from the repository, or from one of the crates' `src/`), and every `umesh_*::module`
/// path they name starts with a module of that crate.
#[test]
fn every_file_and_module_the_docs_name_exists() {
    let root = workspace();
    let bases = ["", "src", "crates/umesh-core/src", "crates/umesh-net/src", "crates/umesh-workflow/src"];
    let crates = crates();
    let mut missing = Vec::new();
    let mut docs = vec!["README.md".to_string(), "ARCHITECTURE.md".to_string()];
    for entry in std::fs::read_dir(root.join("docs")).expect("read docs/") {
        let name = entry.expect("a docs/ entry").file_name().to_string_lossy().into_owned();
        if name.ends_with(".md") {
            docs.push(format!("docs/{name}"));
        }
    }
    for doc in &docs {
        let text = std::fs::read_to_string(root.join(doc)).expect("read the doc");
        for (k, span) in text.split('`').enumerate() {
            if k % 2 == 0 {
                continue;
            }
            let token = span.trim().trim_end_matches(['.', ',']);
            let is_path = token.contains('/')
                && !token.starts_with("../")
                && !token.contains(' ')
                && [".rs", ".sh", ".md", ".toml"].iter().any(|e| token.ends_with(e));
            if is_path && !bases.iter().any(|b| root.join(b).join(token).exists()) {
                missing.push(format!("{doc}: `{token}`"));
            }
            let mut parts = token.split("::");
            let krate = match parts.next() {
                Some("umesh_core") => &crates[0],
                Some("umesh_net") => &crates[1],
                Some("umesh_workflow") => &crates[3],
                _ => continue,
            };
            let Some(first) = parts.next() else { continue };
            let first = first.trim_end_matches("()");
            let is_module = krate.files.contains_key(&vec![first.to_string()]);
            let is_root_item = krate.files[&Vec::new()].code.contains(first);
            if !(is_module || is_root_item) {
                missing.push(format!("{doc}: `{token}` ({} has no `{first}`)", krate.name));
            }
        }
    }
    assert!(missing.is_empty(), "named in the docs but not in the tree:\n{}", missing.join("\n"));
}

/// The README, ARCHITECTURE.md and docs/ speak to users of the program: how the figures got
/// there belongs in CHANGELOG.md. No issue numbers or references to the issue tracker, no
/// numbered rounds of work or sessions, no "the build before".
#[test]
fn the_docs_name_no_issues_rounds_of_work_or_earlier_builds() {
    let root = workspace();
    let mut docs = vec![root.join("README.md"), root.join("ARCHITECTURE.md")];
    for entry in std::fs::read_dir(root.join("docs")).expect("read docs/") {
        let p = entry.expect("a docs/ entry").path();
        if p.extension().is_some_and(|e| e == "md") {
            docs.push(p);
        }
    }
    let ordinals = ["first", "second", "third", "fourth", "fifth", "sixth", "seventh", "eighth", "ninth", "tenth"];
    let mut found = Vec::new();
    for doc in &docs {
        let text = std::fs::read_to_string(doc).expect("read the doc").to_lowercase();
        let words: Vec<&str> =
            text.split(|c: char| !(c.is_alphanumeric() || c == '#' || c == '\'')).filter(|w| !w.is_empty()).collect();
        for (k, w) in words.iter().enumerate() {
            let next = words.get(k + 1).copied().unwrap_or("");
            let numbered = |s: &str| s.trim_start_matches('#').chars().next().is_some_and(|c| c.is_ascii_digit());
            let ordinal = |s: &str| {
                ordinals.contains(&s) || (s.ends_with("th") && s.chars().next().is_some_and(|c| c.is_ascii_digit()))
            };
            let hit = match *w {
                "issue" | "issues" | "issue's" => true,
                "session" | "sessions" | "round" | "rounds" => numbered(next) || k > 0 && ordinal(words[k - 1]),
                w if w.starts_with('#') && numbered(w) => true,
                _ => false,
            };
            if hit {
                let context = words[k.saturating_sub(3)..(k + 3).min(words.len())].join(" ");
                found.push(format!("{}: \"{context}\"", doc.strip_prefix(&root).unwrap_or(doc).display()));
            }
        }
        for phrase in ["the build before", "the model before", "the builds before", "round of work", "rounds of work"] {
            if text.contains(phrase) {
                found.push(format!("{}: \"{phrase}\"", doc.strip_prefix(&root).unwrap_or(doc).display()));
            }
        }
    }
    assert!(
        found.is_empty(),
        "development history in the user docs (it belongs in CHANGELOG.md):\n{}",
        found.join("\n")
    );
}
